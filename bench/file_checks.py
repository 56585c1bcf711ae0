"""What reading a mesh file's declarations costs (core/meshes/file_checks.py): the time
of `check_declared` beside the whole `read_mesh` for one mesh written in each format.

    python bench/file_checks.py [--subdivisions 7] [--folder DIR]

The mesh is trimesh's icosphere (subdivisions 7: 163,842 vertices, 327,680 faces), written
by trimesh in each format into a temporary folder (or `--folder`).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import trimesh

from shapegen_core.meshes.file_checks import check_declared
from shapegen_core.meshes.reading import read_mesh

FORMATS = {"off": ("off", {}), "obj": ("obj", {}), "ply_ascii": ("ply", {"encoding": "ascii"}),
           "ply_binary": ("ply", {"encoding": "binary"}), "stl_ascii": ("stl_ascii", {}), "stl_binary": ("stl", {}),
           "glb": ("glb", {})}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--subdivisions", type=int, default=7)
    parser.add_argument("--folder", type=Path, default=None)
    args = parser.parse_args(argv)
    sphere = trimesh.creation.icosphere(args.subdivisions)
    with tempfile.TemporaryDirectory(prefix="shapegen-bench-") as temporary:
        folder = args.folder or Path(temporary)
        print(f"| format | vertices | check_declared (s) | read_mesh (s) |\n|---|---|---|---|")
        for name, (file_type, options) in FORMATS.items():
            data = sphere.export(file_type=file_type, **options)
            path = folder / f"sphere_{name}.{file_type.split('_')[0]}"
            path.write_bytes(data.encode() if isinstance(data, str) else data)
            start = time.perf_counter()
            check_declared(path)
            checked = time.perf_counter() - start
            start = time.perf_counter()
            read_mesh(path)
            print(f"| {name} | {len(sphere.vertices)} | {checked:.2f} | {time.perf_counter() - start:.2f} |")


if __name__ == "__main__":
    main()
