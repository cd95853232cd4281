"""Packaging: `pip install .` is the library and CLI without the service stack, `.[service]` adds
the service, every import is declared, torch is a range in the package and one pin in
constraints.txt for our own installs, `bench` is neither installed nor shipped, and the wheel carries
the job store migrations."""

from __future__ import annotations

import ast
import re
import shutil
import subprocess
import sys
import zipfile
from importlib.metadata import PackageNotFoundError, distribution, packages_distributions
from pathlib import Path

from packaging.requirements import Requirement
from packaging.version import Version

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

REPO = Path(__file__).resolve().parent.parent
SERVICE_TOP_MODULES = ("fastapi", "starlette", "uvicorn", "python_multipart", "pydantic_settings",
                       "sqlalchemy", "alembic", "psycopg", "celery", "kombu", "redis", "boto3", "botocore")


def project() -> dict:
    return tomllib.loads((REPO / "pyproject.toml").read_text())["project"]


def canonical(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def requirements(specs: list[str]) -> dict[str, Requirement]:
    return {canonical(r.name): r for r in map(Requirement, specs)}


def imported_top_modules(package: str) -> set[str]:
    """Top-level modules imported anywhere in ``package`` (module level and inside functions)."""
    found = set()
    for path in (REPO / package).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                found.update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                found.add(node.module.split(".")[0])
    return found - set(sys.stdlib_module_names) - {"__future__"}


def distributions_of(module: str) -> set[str]:
    found = {canonical(d) for d in packages_distributions().get(module, [])}
    if not found:   # a bare extension module (xatlas) is missing from that map before Python 3.12
        try:
            found = {canonical(distribution(module).metadata["Name"])}
        except PackageNotFoundError:
            pass
    return found


def test_core_and_service_dependencies_are_split():
    core = requirements(project()["dependencies"])
    service = requirements(project()["optional-dependencies"]["service"])
    for module in SERVICE_TOP_MODULES:
        dists = distributions_of(module)
        assert dists, f"{module} is not installed here, cannot check it"
        assert not dists & set(core), f"{module} ({dists}) must not be a core dependency"
    assert {"fastapi", "uvicorn", "python-multipart", "pydantic-settings", "sqlalchemy", "psycopg",
            "celery", "redis", "alembic"} <= set(service)
    assert "binary" in service["psycopg"].extras and "standard" in service["uvicorn"].extras


def test_python_multipart_floor_provides_the_module_the_api_imports():
    """`python_multipart` (imported by api/uploads.py) exists from 0.0.13; older releases are `multipart`."""
    assert "python_multipart" in imported_top_modules("api")
    spec = requirements(project()["optional-dependencies"]["service"])["python-multipart"].specifier
    floor = min(Version(s.version) for s in spec if s.operator == ">=")
    assert floor >= Version("0.0.13")
    assert not spec.contains("0.0.12") and spec.contains("0.0.34")


def test_every_import_is_a_declared_dependency():
    core = set(requirements(project()["dependencies"]))
    service = set(requirements(project()["optional-dependencies"]["service"]))
    own = {"nepf_core", "nepf_json", "api", "worker", "jobstore"}
    for package, allowed in (("nepf_core", core), ("nepf_json", set()), ("jobstore", service), ("api", core | service),
                             ("worker", core | service)):
        for module in imported_top_modules(package) - own:
            dists = distributions_of(module)
            assert dists & allowed, f"{package}/ imports {module} ({dists or 'not installed'}), not declared"


def test_library_and_cli_import_without_the_service_packages():
    """A `pip install .` without extras: nothing in nepf_core imports the service stack, `nepf
    --help` works, and the service commands say how to install the service."""
    blocked = ", ".join(repr(m) for m in SERVICE_TOP_MODULES)
    script = f"""
import importlib, io, pkgutil, sys, contextlib
BLOCKED = {{{blocked}}}
class Refuse:
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
sys.meta_path.insert(0, Refuse())
try:
    import fastapi
    raise SystemExit("the blocker does not work")
except ModuleNotFoundError:
    pass
import nepf_core
for m in pkgutil.walk_packages(nepf_core.__path__, "nepf_core."):
    importlib.import_module(m.name)
from nepf_core.cli import main
out = io.StringIO()
with contextlib.redirect_stdout(out):
    try:
        main(["--help"])
    except SystemExit as e:
        assert e.code == 0, e.code
assert "fit" in out.getvalue() and "serve" in out.getvalue(), out.getvalue()
for cmd in ("serve", "worker", "token"):
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        rc = main([cmd])
    assert rc == 2 and "install nepf[service]" in err.getvalue(), (cmd, rc, err.getvalue())
leaked = sorted(k for k in sys.modules if k.split(".")[0] in BLOCKED)
assert not leaked, leaked
print("ok")
"""
    r = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stdout[-2000:] + r.stderr[-4000:]


def constraint_pins() -> dict[str, str]:
    """``{name: version}`` of the ``==`` lines of constraints.txt."""
    pins = {}
    for line in (REPO / "constraints.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            req = Requirement(line)
            (spec,) = req.specifier
            assert spec.operator == "==", f"constraints.txt: {line} is not an exact pin"
            pins[canonical(req.name)] = spec.version
    return pins


def pip_install_lines(text: str) -> list[str]:
    """The ``pip install`` commands of a shell script or Dockerfile, continuation lines joined."""
    joined = re.sub(r"\\\n\s*", " ", text)
    return [ln.strip() for ln in joined.splitlines() if re.search(r"\bpip\b.*\binstall\b", ln)
            and not ln.lstrip().startswith("#")]


def test_torch_is_a_range_in_the_package_and_one_pin_for_our_installs():
    """pyproject.toml bounds torch (an existing environment keeps its own); constraints.txt pins the
    version the benchmarks were measured with, inside that range; scripts/install.sh (and so CI:
    .ci/run calls it), the Dockerfile and the benchmarks use that file and write no version of
    their own; the CUDA image's documented index carries every release."""
    (torch,) = [r for r in map(Requirement, project()["dependencies"]) if r.name == "torch"]
    assert "==" not in {s.operator for s in torch.specifier}, "the library must not pin torch exactly"
    pin = constraint_pins()["torch"]
    assert torch.specifier.contains(pin), f"constraints.txt pins torch {pin}, outside pyproject's {torch.specifier}"
    assert not torch.specifier.contains("3.0") and not torch.specifier.contains("2.3.1")
    assert "bash scripts/install.sh" in (REPO / ".ci" / "run").read_text()
    for name in ("scripts/install.sh", "Dockerfile"):
        text = (REPO / name).read_text()
        code = "\n".join(ln for ln in text.splitlines() if not ln.lstrip().startswith("#"))
        assert not re.search(r"torch\s*[=<>~!]=?\s*\d", code), f"{name} writes its own torch version"
        lines = pip_install_lines(text)
        installs = [ln for ln in lines if re.search(r"\btorch\b|\.\[", ln)]
        assert any(re.search(r"\btorch\b", ln) for ln in installs), f"{name} does not install torch first"
        assert any(".[" in ln for ln in installs), f"{name} does not install the package"
        for ln in installs:   # torch and the package: both under the constraints, or pip picks another torch
            assert "-c constraints.txt" in ln, f"{name}: {ln!r} installs without -c constraints.txt"
    docker = (REPO / "Dockerfile").read_text()
    assert re.search(r"^COPY .*constraints\.txt", docker, re.M), "the Dockerfile must copy constraints.txt"
    assert "TORCH_INDEX_URL=https://download.pytorch.org/whl/cu121" not in docker + (REPO / "docker-compose.yml").read_text(), \
        "the cu121 index has no torch " + pin
    assert "TORCH_INDEX_URL=https://pypi.org/simple" in docker   # PyPI's Linux wheel: a CUDA build of every release
    sys.path.insert(0, str(REPO))
    from bench.run import pinned_version
    assert pinned_version("torch") == pin
    for name in ("README.md", "docs/SERVICE.md"):
        for version in re.findall(r"torch\s*==\s*([\w.+]+)", (REPO / name).read_text()):
            assert version == pin, f"{name} says torch=={version}, constraints.txt pins {pin}"


def test_bench_is_not_installed_nor_shipped_but_runs_from_the_repo():
    find = tomllib.loads((REPO / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"]
    assert not any(p.startswith("bench") for p in find["include"])
    assert "bench" in (REPO / ".dockerignore").read_text().split()
    assert not re.search(r"^COPY\s+bench", (REPO / "Dockerfile").read_text(), re.M)
    r = subprocess.run([sys.executable, "-m", "bench", "--help"], cwd=REPO, capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 0 and "python -m bench" in r.stdout, r.stderr


def test_wheel_ships_the_migrations_and_not_bench(tmp_path):
    """Built from a copy of the sources (setuptools writes build/ beside the sources)."""
    src = tmp_path / "src"
    for name in ("nepf_core", "nepf_json", "jobstore", "api", "worker", "bench", "tests"):
        shutil.copytree(REPO / name, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(REPO / name, src / name)
    r = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "-q",
                        "-w", str(tmp_path / "dist"), str(src)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    (wheel,) = (tmp_path / "dist").glob("nepf-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    versions = sorted(p.name for p in (REPO / "jobstore/migrations/versions").glob("0*.py"))
    assert versions and {f"jobstore/migrations/versions/{v}" for v in versions} <= names
    assert {"jobstore/migrations/env.py", "jobstore/migrations/script.py.mako", "nepf_core/cli.py",
            "nepf_json/__init__.py", "api/main.py", "worker/tasks.py"} <= names
    assert not any(n.startswith(("bench/", "tests/")) for n in names)
