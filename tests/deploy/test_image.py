"""The Dockerfile, read with Docker's own parser (the ``dockerfile`` package wraps BuildKit's),
installs what the README says: a Python the project supports, Debian's libLLVM for Mitsuba's
fast variant, and the project from the files it copies. Without an engine, the install itself
is replayed: the files copied before ``pip install .`` are built into a wheel as the image does,
and the four services and the ``cosmos`` command are imported from it alone."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import tomllib
import zipfile
from pathlib import Path
from typing import NamedTuple

import pytest

from tests.deploy.image import WORKDIR, copied_before_install, env, of
from tests.deploy.manifests import IMAGE_SERVICES
from tests.support import ROOT


def test_the_image_has_a_python_the_project_supports():
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    [base] = of("FROM")
    match = re.fullmatch(r"python:(\d+)\.(\d+)-slim-\w+", base.value[0])
    assert match, base.value
    least = re.fullmatch(r">=(\d+)\.(\d+)", pyproject["project"]["requires-python"])
    assert least
    assert tuple(map(int, match.groups())) >= tuple(map(int, least.groups()))


def test_the_image_installs_the_libllvm_the_readme_names():
    [package] = re.findall(r"Debian's `(libllvm\d+)`", (ROOT / "README.md").read_text())
    [apt] = [run.value[0] for run in of("RUN") if "apt-get install" in run.value[0]]
    assert package in apt.split()
    version = package.removeprefix("libllvm")
    assert f"libLLVM.so.{version}" in env()["DRJIT_LIBLLVM_PATH"]


def test_the_image_copies_the_project_before_installing_it():
    copied = copied_before_install()
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    assert "pyproject.toml" in copied
    assert pyproject["project"]["readme"] in copied  # setuptools reads it to install
    assert {"services", "cosmos"} <= set(copied)


def test_the_image_finds_its_scenes_and_model_where_it_copied_them():
    variables = env()
    destinations = {  # the folders copied, by where they land
        f"{WORKDIR}/{copy.value[1].removeprefix('./')}": copy.value[0]
        for copy in of("COPY")
        if len(copy.value) == 2 and (ROOT / copy.value[0]).is_dir()
    }
    for variable in ("COSMOS_SCENES_DIR", "COSMOS_DETECTOR_MODEL"):
        path = Path(variables[variable])
        source = next(
            ROOT / src / path.relative_to(dest)
            for dest, src in destinations.items()
            if path.is_relative_to(dest)
        )
        assert source.exists(), f"{variable}={path} is {source} here, which does not exist"


def test_the_image_serves_on_the_ports_it_exposes():
    [expose] = of("EXPOSE")
    assert set(expose.value) == {"8000", "8001", "8002", "8003"}
    [command] = of("CMD")
    assert "services.${SERVICE}.app:app" in command.value[-1]
    assert "--port ${PORT}" in command.value[-1]


def test_secrets_stay_out_of_the_build_context():
    ignored = set((ROOT / ".dockerignore").read_text().split())
    assert {".env", "data", "**/secrets.env"} <= ignored


def _git_files(*paths: str) -> list[str]:
    listed = subprocess.run(
        ["git", "ls-files", "--", *paths], cwd=ROOT, capture_output=True, text=True, check=True
    )
    return listed.stdout.split()


def _top_level_packages() -> set[str]:
    return {path.split("/")[0] for path in _git_files("*/__init__.py") if path.count("/") == 1}


class Installed(NamedTuple):
    wheel: Path
    site: Path


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Installed:
    """The project as the image installs it: the files copied before ``pip install .``, built
    into a wheel and installed on their own (dependencies are the test environment's)."""
    context = tmp_path_factory.mktemp("context")
    for path in _git_files(*copied_before_install()):
        (context / path).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / path, context / path)
    wheels = tmp_path_factory.mktemp("wheels")
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    build = [*pip, "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-w", str(wheels)]
    subprocess.run([*build, str(context)], check=True, capture_output=True, timeout=300)
    [wheel] = wheels.glob("*.whl")
    target = tmp_path_factory.mktemp("site")
    install = [*pip, "install", "--no-deps", "--no-index", "--target", str(target), str(wheel)]
    subprocess.run(install, check=True, capture_output=True, timeout=300)
    return Installed(wheel, target)


def test_the_installed_project_holds_every_file_of_the_copied_packages(installed: Installed):
    packages = [path for path in copied_before_install() if (ROOT / path).is_dir()]
    with zipfile.ZipFile(installed.wheel) as wheel:
        names = set(wheel.namelist())
        [entry_points] = [name for name in names if name.endswith(".dist-info/entry_points.txt")]
        scripts = wheel.read(entry_points).decode()
    missing = [path for path in _git_files(*packages) if path not in names]
    assert not missing, f"pip install . in the image leaves out {missing}"
    assert re.search(r"^cosmos = cosmos\.cli:main$", scripts, re.MULTILINE)


def _environment_without_the_project() -> dict[str, str]:
    """This environment less the project's settings and its PYTHONPATH (the worktree)."""
    return {
        name: value
        for name, value in os.environ.items()
        if not name.startswith("COSMOS_") and name != "PYTHONPATH"
    }


IMPORT_FROM_THE_IMAGE = """
import importlib, importlib.abc, sys
absent = set(sys.argv[1].split(","))
class NotInTheImage(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in absent:
            raise ModuleNotFoundError(f"{name} is not in the image", name=name)
sys.meta_path.insert(0, NotInTheImage())
for service in sys.argv[2].split(","):
    app = importlib.import_module(f"services.{service}.app")
    assert app.__file__.startswith(sys.argv[3]), app.__file__
from cosmos.cli import main
raise SystemExit(main(["keys", "list", "--database-url", sys.argv[4]]))
"""


def test_the_services_and_the_cosmos_command_run_from_what_the_image_installs(
    installed: Installed, tmp_path: Path
):
    site = installed.site
    copied = {path for path in copied_before_install() if (ROOT / path).is_dir()}
    absent = _top_level_packages() - copied
    assert "training" in absent  # the image has no training extra
    database = f"sqlite:///{tmp_path}/controller.sqlite3"
    arguments = [",".join(sorted(absent)), ",".join(IMAGE_SERVICES), str(site), database]
    ran = subprocess.run(
        [sys.executable, "-c", IMPORT_FROM_THE_IMAGE, *arguments],
        cwd=tmp_path,
        env=_environment_without_the_project() | {"PYTHONPATH": str(site)},
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert ran.returncode == 0, ran.stderr[-3000:]
    assert "created (UTC)" in ran.stdout
