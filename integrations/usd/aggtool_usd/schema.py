"""The codeless `AggtoolAggregate` schema (resources/): a Boundable prim type for the sidecar,
registered with USD's plugin registry when the package is imported."""
from __future__ import annotations

from pathlib import Path

from pxr import Plug, Usd

RESOURCES = Path(__file__).resolve().parent / "resources"
#: The prim type of the `aggregate` level.
AGGREGATE_TYPE = "AggtoolAggregate"


def register() -> bool:
    """Registers the schema (once); True when USD then knows the type. Registration must come
    before the schema registry is first built in this process; when it is too late the prim is
    still written with its type name and attributes, only untyped for this process."""
    Plug.Registry().RegisterPlugins(str(RESOURCES))
    return bool(Usd.SchemaRegistry().FindConcretePrimDefinition(AGGREGATE_TYPE))
