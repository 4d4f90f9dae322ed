"""A guard against silent skips (pytest hooks that tests/conftest.py imports).

With ``DOFSPLAT_MAX_SKIPS=N`` in the environment, a run in which more than N tests skip
fails (exit status 1) and lists each skip's reason: a test that stops running (a tool no
longer installs, shared data moved) would otherwise pass unnoticed. Tests marked ``cuda``
are counted apart: without a GPU they skip in every run but the simulator's
(``pytest --cudasim``, tests/cudasim.py), which runs them; with ``DOFSPLAT_REQUIRE_CUDA=1`` (they
must run) they count like the others.
"""

from __future__ import annotations

import os

import pytest

LIMIT = "DOFSPLAT_MAX_SKIPS"


def pytest_configure(config):
    config.addinivalue_line(
        "markers", "cuda: runs the CUDA backend, on a GPU or on numba's CUDA simulator "
                   "(skips without either; not counted by DOFSPLAT_MAX_SKIPS)")


def _skips(reporter) -> tuple[list, list]:
    """(counted, cuda): the run's skip reports, those of ``cuda`` tests apart."""
    reports = reporter.stats.get("skipped", []) if reporter is not None else []
    if os.environ.get("DOFSPLAT_REQUIRE_CUDA") == "1":
        return reports, []
    cuda = [r for r in reports if "cuda" in getattr(r, "keywords", {})]
    return [r for r in reports if r not in cuda], cuda


def _reason(report) -> str:
    if isinstance(report.longrepr, tuple):  # (path, line, "Skipped: reason")
        return report.longrepr[2].removeprefix("Skipped: ")
    return str(report.longrepr)


@pytest.hookimpl(trylast=True)
def pytest_sessionfinish(session, exitstatus):
    limit = os.environ.get(LIMIT)
    if limit is None or exitstatus != pytest.ExitCode.OK:
        return
    counted, _ = _skips(session.config.pluginmanager.get_plugin("terminalreporter"))
    if len(counted) > int(limit):
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    limit = os.environ.get(LIMIT)
    if limit is None:
        return
    counted, cuda = _skips(terminalreporter)
    over = len(counted) > int(limit)
    terminalreporter.section("skips", sep="-", red=over, bold=over)
    write = terminalreporter.write_line
    if over:
        write(f"FAILED: skipped {len(counted)}, more than {LIMIT}={limit}:", red=True)
        for r in counted:
            write(f"  {r.nodeid}: {_reason(r)}")
    else:
        write(f"skipped {len(counted)}, at most {LIMIT}={limit}")
    if cuda:
        write(f"and {len(cuda)} CUDA test(s), not counted: without a GPU they run on numba's CUDA "
              "simulator (pytest --cudasim)")
