"""USD for aggtool: asset layers whose UsdLod root switches between an asset's mesh and its
`.agg` aggregate, and PointInstancer assemblies from aggtool manifests (and back).

    python -m aggtool_usd asset ASSET [--agg ASSET.agg] -o ASSET.usda
    python -m aggtool_usd assembly MANIFEST.json -o city.usda
    python -m aggtool_usd manifest city.usda -o MANIFEST.json

The geometry comes from the aggtool binary (`aggtool export`; found through $AGGTOOL, the
repository's target/ builds, or PATH), since usd-core reads neither glTF nor OBJ.
"""
from . import schema

schema.register()

from .asset import write_asset  # noqa: E402  (after the schema is registered)
from .assembly import read_manifest, write_assembly, write_manifest  # noqa: E402
from .errors import UsdToolError  # noqa: E402
from .manifest import load_manifest  # noqa: E402

__all__ = ["write_asset", "write_assembly", "read_manifest", "write_manifest", "load_manifest", "UsdToolError"]
__version__ = "0.1.0"
