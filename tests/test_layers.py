"""The import contract: the stages import one way (DESIGN.md, STYLE.md).

imaging and registration import no other stage of the project; meshing imports imaging and
``mechanics.mesh`` only; mechanics imports the standard library, numpy and scipy (and the
optional accelerators it guards); none of them imports ``breastmodel``.
"""

import ast
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PROJECT = {"imaging", "registration", "meshing", "mechanics", "breastmodel"}
STDLIB = set(sys.stdlib_module_names)

#: package -> project modules it may import (prefix match on dotted names)
ALLOWED_PROJECT = {
    "imaging": {"imaging"},
    "registration": {"registration"},
    "meshing": {"meshing", "imaging", "mechanics.mesh"},
    "mechanics": {"mechanics"},
}
#: third-party packages mechanics may import (the accelerators are optional, guarded)
MECHANICS_THIRD_PARTY = {"numpy", "scipy", "threadpoolctl", "pypardiso"}


def imports(path: Path, pkg: str | None = None) -> list[tuple[int, str]]:
    """(line, dotted module) of every import in a file; relative imports are resolved
    against ``pkg`` (default: the file's package under the repository root)."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    if pkg is None:
        pkg = ".".join(path.relative_to(ROOT).with_suffix("").parts[:-1])
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg.split(".")[: len(pkg.split(".")) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            out.append((node.lineno, mod))
            out += [(node.lineno, f"{mod}.{a.name}") for a in node.names
                    if mod.split(".")[0] in PROJECT]
    return out


def _allowed(package: str, module: str) -> bool:
    top = module.split(".")[0]
    if top in PROJECT:
        return any(module == a or module.startswith(a + ".")
                   for a in ALLOWED_PROJECT[package]) or (
            # "from mechanics import mesh" names the module mechanics.mesh
            package == "meshing" and module == "mechanics")
    if package == "mechanics":
        return top in STDLIB or top in MECHANICS_THIRD_PARTY or top == "__future__"
    return True


@pytest.mark.parametrize("package", sorted(ALLOWED_PROJECT))
def test_stage_imports_follow_the_contract(package):
    bad = []
    for path in sorted((ROOT / package).rglob("*.py")):
        for line, mod in imports(path):
            if not _allowed(package, mod):
                bad.append(f"{path.relative_to(ROOT)}:{line}: imports {mod}")
    assert not bad, "import contract broken:\n" + "\n".join(bad)


def test_the_contract_catches_a_violation(tmp_path):
    f = tmp_path / "probe.py"
    f.write_text("import SimpleITK\nfrom breastmodel import cli\nfrom . import mesh\n")
    mods = [m for _, m in imports(f, "mechanics")]
    assert "mechanics.mesh" in mods  # relative import resolved
    assert not _allowed("mechanics", "SimpleITK")
    assert not _allowed("mechanics", "breastmodel.cli")
    assert not _allowed("meshing", "mechanics.solver")
    assert _allowed("meshing", "mechanics.mesh")


#: what an install of the imaging and meshing stages adds to numpy and scipy
IMAGING_STACK = ("SimpleITK", "skimage", "cv2", "pymeshlab", "pytetwild", "open3d", "meshio",
                 "pyvista", "dask", "distributed", "tomli_w", "matplotlib")


def test_mechanics_tests_load_with_numpy_and_scipy_alone():
    """Every module of tests/mechanics (and the helpers they import) loads with the imaging
    stack made unimportable: the solver's tests need numpy and scipy only."""
    import subprocess

    script = (
        "import importlib, pathlib, sys\n"
        f"for m in {IMAGING_STACK!r}:\n"
        "    sys.modules[m] = None\n"
        f"sys.path[:0] = [{str(ROOT)!r}, {str(ROOT / 'tests')!r}, "
        f"{str(ROOT / 'tests' / 'mechanics')!r}]\n"
        f"for p in sorted(pathlib.Path({str(ROOT / 'tests' / 'mechanics')!r})"
        ".glob('test_*.py')):\n"
        "    importlib.import_module(p.stem)\n"
        "print('ok')\n")
    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                          timeout=300, cwd=ROOT)
    assert done.returncode == 0 and done.stdout.strip() == "ok", done.stderr[-2000:]
