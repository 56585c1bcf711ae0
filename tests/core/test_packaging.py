"""The installed `shapegen_core` must hold every sub-package of `core/`.

pyproject.toml lists the packages by hand; a new folder that is not added there would
work in the editable checkout and be missing from a real install. This builds the wheel
(setuptools, no network) and compares its packages with the folders of core/.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
CORE = ROOT / "core"


def core_packages() -> set[str]:
    """Dotted names of every folder of core/ that holds Python modules."""
    names = set()
    for init in CORE.rglob("*.py"):
        if "__pycache__" in init.parts:
            continue
        relative = init.parent.relative_to(CORE)
        names.add(".".join(("shapegen_core", *relative.parts)))
    return names


def test_every_core_folder_is_a_package():
    for name in core_packages():
        folder = CORE.joinpath(*name.split(".")[1:])
        assert (folder / "__init__.py").is_file(), f"{folder} holds modules but no __init__.py"


def test_pyproject_lists_every_core_package():
    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    assert core_packages() <= listed, f"missing from pyproject.toml: {sorted(core_packages() - listed)}"


def test_built_wheel_holds_every_core_module(tmp_path):
    # build from a copy: setuptools would reuse a stale build/ folder of the checkout
    source = tmp_path / "source"
    source.mkdir()
    shutil.copy(ROOT / "pyproject.toml", source)
    shutil.copytree(CORE, source / "core", ignore=shutil.ignore_patterns("__pycache__"))
    wheels = tmp_path / "wheels"
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
         "--disable-pip-version-check", "-q", "-w", str(wheels), str(source)],
        check=True, capture_output=True, cwd=tmp_path,
    )
    (wheel,) = wheels.glob("shapegen-*.whl")
    with zipfile.ZipFile(wheel) as archive:
        shipped = {name for name in archive.namelist() if name.endswith(".py")}
    expected = {
        "shapegen_core/" + path.relative_to(CORE).as_posix()
        for path in CORE.rglob("*.py") if "__pycache__" not in path.parts
    }
    assert expected <= shipped, f"modules missing from the wheel: {sorted(expected - shipped)}"


def _architecture_modules() -> str:
    text = (ROOT / "docs" / "architecture.md").read_text()
    return text[text.index("## Modules"):]


def test_architecture_names_every_module():
    """docs/architecture.md's module table is the map of the tree: every module and package
    of core/ and shapegen_addon/ is named there (in backticks), so a new file cannot hide."""
    layout = _architecture_modules()
    missing = []
    for top in ("core", "shapegen_addon"):
        for path in (ROOT / top).rglob("*.py"):
            if "__pycache__" in path.parts:
                continue
            name = path.parent.name if path.name == "__init__.py" else path.stem
            if path.name == "__init__.py" and path.parent.name == top:
                continue
            if f"`{name}`" not in layout and f"{name}/`" not in layout and f"/{name}.py`" not in layout:
                missing.append(str(path.relative_to(ROOT)))
    assert not missing, f"docs/architecture.md does not name: {missing}"


def test_every_path_the_docs_name_exists():
    """Every repository path the README and docs/ name in backticks or links exists: the
    docs point at nothing outside the repository and at nothing that was removed."""
    pattern = re.compile(r"`((?:core|shapegen_addon|tests|bench|scripts|docs|requirements)/[\w./-]*)`"
                         r"|\]\(((?!https?:)[^)#]+)\)")
    missing = []
    for page in [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]:
        for match in pattern.finditer(page.read_text()):
            path = match.group(1) or match.group(2)
            base = ROOT if match.group(1) else page.parent
            if not (base / path).exists():
                missing.append(f"{page.name}: {path}")
    assert not missing, missing


def test_every_method_section_the_code_cites_exists():
    """Code cites docs/method.md by its numbered sections ("docs/method.md §3"); each
    exists there as a heading "## 3. ..."."""
    headings = set(re.findall(r"^## (\d+)\. ", (ROOT / "docs" / "method.md").read_text(), flags=re.MULTILINE))
    cited = {}
    for top in ("core", "shapegen_addon", "bench", "scripts"):
        for path in (ROOT / top).rglob("*.py"):
            for section in re.findall(r"method\.md §(\d+)", path.read_text()):
                cited.setdefault(section, path.relative_to(ROOT).as_posix())
    assert cited, "no code cites docs/method.md"
    missing = {section: path for section, path in cited.items() if section not in headings}
    assert not missing, f"sections cited but missing from docs/method.md: {missing}"


def test_readme_is_short_and_opens_with_the_two_set_up_commands():
    """A newcomer finds set-up first and the whole page on a few screens."""
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= 150
    first_block = lines[lines.index("```sh") + 1:lines.index("```", lines.index("```sh") + 1)]
    assert [line.split()[:2] for line in first_block] == [["make", "demo"], ["make", "test"]]
    headings = [line for line in lines if line.startswith("## ")]
    for wanted in ("Install into Blender", "The artist's path", "Pipelines", "Read more"):
        assert any(wanted in heading for heading in headings), wanted


def test_version_is_one_number_for_the_cli_the_package_and_the_extension(capsys):
    """`shapegen --version` prints the version pyproject.toml and blender_manifest.toml
    declare (one number for the pip package and the Blender extension)."""
    from shapegen_core.app.cli import main

    with pytest.raises(SystemExit) as stop:
        main(["--version"])
    assert stop.value.code == 0
    package = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]["version"]
    extension = tomllib.loads((ROOT / "blender_manifest.toml").read_text())["version"]
    assert package == extension
    assert capsys.readouterr().out.split() == ["shapegen", package]


#: the most `.py` modules the top of core/ may hold besides __init__.py: the rest live in
#: the folders that are its layers
TOP_MODULES = 12
#: the longest a module of core/ or shapegen_addon/ may be
MODULE_LINES = 500


def _pictured_layers() -> list[str]:
    """The folders of core/ in the picture of docs/architecture.md's "Layers", top down."""
    text = (ROOT / "docs" / "architecture.md").read_text()
    picture = text[text.index("## Layers"):]
    picture = picture[picture.index("```") + 3:]
    picture = picture[:picture.index("```")]
    core = picture[picture.index("core (no bpy)"):]
    return re.findall(r"^(?:core \(no bpy\))?\s+([a-z_]+)/\s", core, flags=re.MULTILINE)


def _core_imports() -> dict[str, set[str]]:
    """For each folder of core/ (or top-level module), the others its modules import."""
    import ast

    found: dict[str, set[str]] = {}
    for path in CORE.rglob("*.py"):
        if "__pycache__" in path.parts:
            continue
        parts = path.relative_to(CORE).with_suffix("").parts
        package = parts[:-1]
        layer = parts[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.level:
                target = list(package[:len(package) - (node.level - 1)]) + (node.module.split(".") if node.module else [])
                names = target[:1] or [alias.name for alias in node.names]
                found.setdefault(layer, set()).update(name for name in names if name != layer)
    return found


def test_the_picture_of_the_layers_is_the_folders():
    """docs/architecture.md draws core/ as its folders, each above every folder it imports
    from: every folder is drawn once, no module imports from a folder drawn above its own,
    and the top of core/ holds at most TOP_MODULES modules."""
    layers = _pictured_layers()
    folders = sorted(path.parent.name for path in CORE.glob("*/__init__.py"))
    assert sorted(layers) == folders, f"drawn {layers}, folders {folders}"
    top = [path.name for path in CORE.glob("*.py") if path.name != "__init__.py"]
    assert len(top) <= TOP_MODULES, top
    height = {layer: len(layers) - index for index, layer in enumerate(layers)}
    upward = {layer: sorted(other for other in imported if other in height and height[other] > height[layer])
              for layer, imported in _core_imports().items() if layer in height}
    upward = {layer: above for layer, above in upward.items() if above}
    assert not upward, f"imports from a folder drawn above: {upward}"


def test_no_module_is_longer_than_the_limit():
    too_long = []
    for top in ("core", "shapegen_addon"):
        for path in (ROOT / top).rglob("*.py"):
            name = path.relative_to(ROOT).as_posix()
            if "__pycache__" not in path.parts and len(path.read_text().splitlines()) > MODULE_LINES:
                too_long.append(name)
    assert not too_long, f"longer than {MODULE_LINES} lines: {too_long}"
