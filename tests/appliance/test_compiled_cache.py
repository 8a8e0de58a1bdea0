"""The kernels' cache directory is named by the sources of the modules that define kernels, and only those."""
from __future__ import annotations

from pathlib import Path

from appliance.compiled import _sources_digest


def _package(root: Path) -> Path:
    (root / "pkg").mkdir()
    (root / "pkg" / "kernels.py").write_text("from appliance.compiled import kernel\n\n\n@kernel\ndef f(x):\n"
                                             "    return x + 1\n")
    (root / "pkg" / "user.py").write_text("from appliance.compiled import cache_is_warm\n\nLIMIT = 1\n")
    return root / "pkg"


def test_a_kernel_edit_changes_the_digest(tmp_path: Path) -> None:
    package = _package(tmp_path)
    before = _sources_digest(package)
    (package / "kernels.py").write_text((package / "kernels.py").read_text().replace("x + 1", "x + 2"))
    assert _sources_digest(package) != before


def test_a_module_that_only_imports_the_compiled_helpers_does_not(tmp_path: Path) -> None:
    package = _package(tmp_path)
    before = _sources_digest(package)
    (package / "user.py").write_text((package / "user.py").read_text().replace("LIMIT = 1", "LIMIT = 2"))
    assert _sources_digest(package) == before
