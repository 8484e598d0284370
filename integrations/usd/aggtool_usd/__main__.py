"""Command line: `python -m aggtool_usd {asset,assembly,manifest} ...` (see `--help`). Errors
print one line on stderr and exit with status 1; no output file is then written."""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pxr import Tf

from .asset import DEFAULT_IMAGE_ASPECT, DEFAULT_IMAGE_WIDTH, write_asset
from .assembly import write_assembly, write_manifest
from .errors import UsdToolError


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m aggtool_usd",
        description="USD layers for aggtool: assets whose UsdLod root switches between the mesh and its "
                    ".agg aggregate, PointInstancer assemblies from manifests, and manifests from stages. "
                    "Errors print one line and exit with status 1, writing nothing.")
    sub = p.add_subparsers(dest="command", required=True)

    def image_options(q: argparse.ArgumentParser) -> None:
        q.add_argument("--image-width", type=int, default=DEFAULT_IMAGE_WIDTH,
                       help="image width in pixels at which the LoD threshold is stated (default %(default)s)")
        q.add_argument("--image-aspect", type=float, default=DEFAULT_IMAGE_ASPECT,
                       help="image width / height for the threshold (default 16/9)")

    a = sub.add_parser("asset", help="write an asset's USD layer: a component whose UsdLod root holds the "
                                     "full mesh (payload) and the aggregate sidecar")
    a.add_argument("asset", type=Path, help="the source scene (.gltf, .glb or .obj)")
    a.add_argument("--agg", type=Path, help="its baked aggregate (default: ASSET with .agg, as `aggtool convert` writes it)")
    a.add_argument("-o", "--output", type=Path, required=True, help="the layer to write (ASSET.usda)")
    image_options(a)

    b = sub.add_parser("assembly", help="write a manifest as a kind=assembly stage with one PointInstancer "
                                        "(asset layers go to OUT_assets/ beside it)")
    b.add_argument("manifest", type=Path, help="an aggtool manifest (JSON, version 1)")
    b.add_argument("-o", "--output", type=Path, required=True, help="the assembly layer to write (city.usda)")
    image_options(b)

    c = sub.add_parser("manifest", help="read the PointInstancers and referenced aggtool assets of a USD stage "
                                        "back into a manifest")
    c.add_argument("stage", type=Path, help="any USD stage placing layers written by `aggtool_usd asset`")
    c.add_argument("-o", "--output", type=Path, required=True, help="the manifest to write (JSON)")
    return p


def main(argv: list[str] | None = None) -> int:
    """Runs one command; returns the exit status."""
    args = _parser().parse_args(argv)
    try:
        if args.command in ("asset", "assembly") and not (args.image_width > 0 and args.image_aspect > 0):
            raise UsdToolError("--image-width and --image-aspect must be positive")
        if args.command == "asset":
            out = write_asset(args.asset, args.agg, args.output, image_width=args.image_width,
                              image_aspect=args.image_aspect).layer
        elif args.command == "assembly":
            out = write_assembly(args.manifest, args.output, image_width=args.image_width,
                                 image_aspect=args.image_aspect)
        else:
            out = write_manifest(args.stage, args.output)
    except UsdToolError as e:
        print(f"aggtool_usd: error: {e}", file=sys.stderr)
        return 1
    except OSError as e:  # unwritable folder, full disk: nothing was renamed into place
        print(f"aggtool_usd: error: {e}", file=sys.stderr)
        return 1
    except Tf.ErrorException as e:  # USD refused to write or read a layer
        print(f"aggtool_usd: error: {' '.join(str(e).split())}", file=sys.stderr)
        return 1
    print(f"output: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
