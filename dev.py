#!/usr/bin/env python3
"""Set up the project's virtual environment on first use, then run the simulated bench or the tests.

    python3 dev.py sim [appliance sim options]   # the main job: the closed loop on simulated devices
    python3 dev.py test [pytest options]         # the test suite

Needs only Python >= 3.11 with pip. The environment lives in ./.venv and is reinstalled only when
pyproject.toml changes, so repeated runs start at once.
"""
from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
STAMP = VENV / ".installed-pyproject-sha256"


def _venv_python() -> Path:
    return VENV / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


def _pyproject_digest() -> str:
    return hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()


def ensure_environment() -> Path:
    python = _venv_python()
    digest = _pyproject_digest()
    if python.exists() and STAMP.exists() and STAMP.read_text().strip() == digest:
        return python
    if sys.version_info < (3, 11):
        sys.exit(f"dev.py: Python >= 3.11 is needed, this is {sys.version.split()[0]}")
    if not python.exists():
        print("dev.py: creating .venv", flush=True)
        venv.EnvBuilder(with_pip=True).create(VENV)
    print("dev.py: installing the project and its test tools into .venv (first run only)", flush=True)
    pip = [str(python), "-m", "pip", "--disable-pip-version-check", "install", "--quiet"]
    # The build backend's notes about editable installs are for packagers, not for someone starting the bench.
    quiet = {**os.environ, "PYTHONWARNINGS": "ignore"}
    subprocess.run([*pip, "--upgrade", "pip"], check=True, env=quiet)
    subprocess.run([*pip, "--editable", f"{ROOT}[test]"], check=True, env=quiet)
    STAMP.write_text(digest + "\n")
    return python


def main(argv: list[str]) -> int:
    if not argv or argv[0] not in {"sim", "test", "appliance"}:
        print(__doc__.strip())
        return 2
    python = ensure_environment()
    command, rest = argv[0], argv[1:]
    if command == "test":
        args = [str(python), "-m", "pytest", *rest]
    elif command == "sim":
        args = [str(python), "-m", "appliance", "sim", *rest]
    else:
        args = [str(python), "-m", "appliance", *rest]
    return subprocess.run(args, cwd=ROOT).returncode


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
