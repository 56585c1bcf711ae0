"""Download the wheels listed in blender_manifest.toml into wheels/ (pip download,
binary only, one exact file per manifest entry). Already present files are kept."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def pip_args_for(filename: str) -> list[str]:
    """pip download arguments that fetch exactly this wheel file."""
    stem = filename[: -len(".whl")]
    name, version, python_tag, abi_tag, platform_tag = stem.split("-")
    args = ["--only-binary=:all:", "--no-deps", f"{name}=={version}"]
    if platform_tag != "any":
        # a compound tag (a.b) lists equivalent platforms: the first one is enough
        args += ["--platform", platform_tag.split(".")[0], "--implementation", "cp",
                 "--python-version", python_tag[2] + "." + python_tag[3:], "--abi", abi_tag]
    return args


def main() -> int:
    manifest = tomllib.loads((ROOT / "blender_manifest.toml").read_text())
    target = ROOT / "wheels"
    target.mkdir(exist_ok=True)
    missing = []
    for entry in manifest.get("wheels", []):
        path = ROOT / entry
        if path.is_file():
            continue
        cmd = [sys.executable, "-m", "pip", "download", "-q", "-d", str(target), *pip_args_for(path.name)]
        print("fetching", path.name, flush=True)
        subprocess.run(cmd, check=True)
        if not path.is_file():
            missing.append(path.name)
    if missing:
        print("pip downloaded other file names than the manifest lists:", ", ".join(missing), file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
