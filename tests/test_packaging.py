"""The wheel a pip user gets: every package of the tree is in it, and models/ and
experiments/scenes/ import as bayespd.models and bayespd.scenes from a fresh venv."""
import shutil
import subprocess
import sys
import tomllib
import venv
import zipfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SITE = next(Path(sys.prefix).glob("lib/python*/site-packages"))


def _packages() -> dict:
    """{package name: folder} as pyproject.toml declares them."""
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    mapped = tool.get("package-dir", {})
    return {name: ROOT / mapped.get(name, name.replace(".", "/")) for name in tool["packages"]}


def test_every_package_folder_is_declared():
    declared = {folder.resolve() for folder in _packages().values()}
    found = {init.parent.resolve() for init in (ROOT / "bayespd").rglob("__init__.py")}
    assert found - declared == set(), "add these packages to pyproject.toml's packages list"
    assert all((folder / "__init__.py").exists() for folder in declared)


def test_wheel_installs_models_and_scenes_under_the_library(tmp_path):
    source = tmp_path / "source"  # a copy, so the build leaves no build/ folder in the tree
    shutil.copytree(ROOT, source, ignore=shutil.ignore_patterns(".*", "runs", "build", "dist", "*.egg-info",
                                                                 "__pycache__", "docs"))
    subprocess.run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "--no-build-isolation",
                    "-w", str(tmp_path), str(source)], check=True, cwd=tmp_path)
    wheel = next(tmp_path.glob("bayespd-*.whl"))
    names = set(zipfile.ZipFile(wheel).namelist())
    assert {"bayespd/models/elastic_plate.py", "bayespd/scenes/notched_plate.py",
            "bayespd/linalg/sparse.py", "bayespd/ensemble/predictive.py"} <= names
    assert not any(n.startswith(("tests/", "experiments/", "models/")) for n in names)
    # a fresh venv: the wheel installed into it, its dependencies read from this environment's
    # site-packages (a plain path entry: this environment's editable install is not loaded)
    env = tmp_path / "venv"
    venv.create(env, with_pip=False)
    env_site = next(env.glob("lib/python*/site-packages"))
    (env_site / "dependencies.pth").write_text(f"{SITE}\n")
    python = env / "bin" / "python"
    subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--quiet", "--no-deps",
                    str(wheel)], check=True, cwd=tmp_path)
    code = ("import bayespd, bayespd.models.elastic_plate as m, bayespd.scenes.notched_plate as s;"
            "print(bayespd.__file__, m.elastic_plate.__module__, m.__file__, s.__file__)")
    out = subprocess.run([str(python), "-c", code], check=True, cwd=tmp_path, capture_output=True,
                         text=True).stdout.split()
    assert out[1] == "bayespd.models.elastic_plate"
    assert all(Path(f).is_relative_to(env_site) for f in (out[0], out[2], out[3])), out


def test_every_module_has_its_test_file():
    """tests/ mirrors the package: bayespd/<package>/<module>.py is tested in
    tests/<package>/test_<module>.py, models/<name>.py in tests/models/test_<name>.py."""
    modules = [m for m in (ROOT / "bayespd").rglob("*.py") if m.name != "__init__.py"]
    modules += [m for m in (ROOT / "models").glob("*.py") if m.name != "__init__.py"]
    missing = []
    for module in modules:
        folder = module.parent.relative_to(ROOT)
        folder = folder.relative_to("bayespd") if folder.parts[0] == "bayespd" else folder
        if not (ROOT / "tests" / folder / f"test_{module.name}").exists():
            missing.append(str(module.relative_to(ROOT)))
    assert missing == []
