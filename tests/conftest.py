"""Settings shared by every test folder.

Hypothesis: the data generation of the property tests is timed by hypothesis's health check;
on the shared 2-core CI machine, under load, generating a case can take longer than that check
allows, which says nothing about the code under test. The check is turned off for speed only;
every other health check, and every example count, stays as each test sets it.
"""

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest
from hypothesis import HealthCheck, settings

settings.register_profile("pregrasp", suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("pregrasp")


@pytest.fixture(scope="session")
def make_views() -> ModuleType:
    """``scripts/make_views.py`` (the generator of the single-view test data) as a module."""
    path = Path(__file__).resolve().parents[1] / "scripts" / "make_views.py"
    spec = importlib.util.spec_from_file_location("make_views", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["make_views"] = mod
    spec.loader.exec_module(mod)
    return mod
