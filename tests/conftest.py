"""Project-wide test options and fixtures.

``--device-url URL`` opts into the contract tests marked ``hardware`` against a real device; without
it those tests are skipped with the reason stated.
"""
from __future__ import annotations

import pytest


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--device-url", action="append", default=[],
                     help="kind=URL of a real device for hardware contract tests, e.g. amplifier=/dev/ttyACM0")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    if config.getoption("--device-url"):
        return
    skip = pytest.mark.skip(reason="needs a real device: pass --device-url kind=URL")
    for item in items:
        if "hardware" in item.keywords:
            item.add_marker(skip)


@pytest.fixture
def device_urls(request: pytest.FixtureRequest) -> dict[str, str]:
    pairs = (entry.split("=", 1) for entry in request.config.getoption("--device-url"))
    return {kind: url for kind, url in pairs}
