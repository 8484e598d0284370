"""aggtool from Python: open and trace `.agg` aggregates, and bake them.

    import aggtool, numpy as np
    scene = aggtool.open("tree.agg")
    rgba = scene.trace(origins, directions, aperture=0.002, lights=aggtool.Lights(), seed=1)
    aggtool.convert("tree.glb", "tree.agg", preset="draft", max_res=32)  # as `aggtool convert`

`aggtool.format` is the schema's generated FlatBuffers reader (flatc --python), which works
without the native module (see integrations/python/agg_info.py); everything else comes from
the native module `aggtool._native`, built with maturin (integrations/python/pyproject.toml).
"""

try:
    from ._native import (  # noqa: F401
        AggError,
        Lights,
        Scene,
        __version__,
        bake_settings,
        cache_stats,
        convert,
        open,
        preset_table,
        presets,
        samples_per_walk,
        set_cache_mib,
    )
except ImportError as _e:  # only the generated reader: the native module is not built here
    _native_error = _e

    def __getattr__(name):
        raise ImportError(
            f"aggtool.{name} needs the native module (build it with `maturin build` in "
            f"integrations/python): {_native_error}"
        )
