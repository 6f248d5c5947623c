"""Rewrite the binary .usdc layers of a generated USD asset as text .usda, repointing the paths to them.

`mujoco-usd-converter` writes its material and mesh libraries as crate (.usdc) layers. The project commits the
asset, so text layers keep reviews and diffs readable. Layers named with `--keep-binary` stay crate files: the
mesh library is hundreds of thousands of numbers nobody reviews (its sources are the MJCF and the meshes'
provenance), and as text it is four times larger and takes seven times longer to open, which every session
recording pays when it composes the asset. Run with any Python that has `pxr` (the converter's own venv in
`make usd-asset`): `python robots/tools/usd_text_layers.py ASSET_DIR [--keep-binary NAME.usdc ...]`.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Collection
from pathlib import Path

from pxr import Sdf, UsdUtils

log = logging.getLogger("usd_text_layers")


def convert_to_text_layers(asset_dir: Path, keep_binary: Collection[str] = ()) -> list[Path]:
    """Export each .usdc under asset_dir (except those named in keep_binary) as .usda, repoint references,
    delete the .usdc; return the new files."""
    crate_files = sorted(p for p in asset_dir.rglob("*.usdc") if p.name not in keep_binary)
    renamed: dict[Path, Path] = {}
    for crate in crate_files:
        text = crate.with_suffix(".usda")
        layer = Sdf.Layer.FindOrOpen(str(crate))
        if layer is None or not layer.Export(str(text)):
            raise RuntimeError(f"could not export {crate} as text; is it a valid USD layer?")
        renamed[crate.resolve()] = text.resolve()

    for path in sorted(asset_dir.rglob("*.usda")):
        layer = Sdf.Layer.FindOrOpen(str(path))
        base = path.parent

        def repoint(asset_path: str, base: Path = base) -> str:
            if asset_path.endswith(".usdc") and (base / asset_path).resolve() in renamed:
                return asset_path[: -len(".usdc")] + ".usda"
            return asset_path

        UsdUtils.ModifyAssetPaths(layer, repoint)
        if layer.dirty:
            layer.Save()

    for crate in crate_files:
        crate.unlink()
    return sorted(renamed.values())


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("asset_dir", type=Path)
    parser.add_argument(
        "--keep-binary", action="append", default=[], metavar="NAME", help="a .usdc file name to leave as is"
    )
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    if not args.asset_dir.is_dir():
        log.error("%s is not a directory; pass the converter's output folder", args.asset_dir)
        return 2
    missing = [name for name in args.keep_binary if not list(args.asset_dir.rglob(name))]
    if missing:
        log.error("--keep-binary %s: no such layer under %s", ", ".join(missing), args.asset_dir)
        return 2
    for path in convert_to_text_layers(args.asset_dir, args.keep_binary):
        log.info("wrote %s", path)
    return 0


if __name__ == "__main__":
    sys.exit(main())
