"""tests/skip_guard.py: more skips than DOFSPLAT_MAX_SKIPS fail the run and are listed;
skips of ``cuda`` tests are counted apart (a small suite run by pytest's own pytester)."""

import pytest

pytest_plugins = ["pytester"]

SUITE = '''
import pytest

def test_runs():
    pass

def test_a():
    pytest.skip("no tool A")

@pytest.mark.skipif(True, reason="no data B")
def test_b():
    pass

@pytest.mark.cuda
@pytest.mark.skipif(True, reason="no GPU")
def test_gpu():
    pass
'''


@pytest.fixture
def suite(pytester):
    pytester.makeconftest("from skip_guard import pytest_configure, pytest_sessionfinish, "
                          "pytest_terminal_summary  # noqa: F401")
    pytester.makepyfile(test_suite=SUITE)
    return pytester


def test_more_skips_than_allowed_fail_and_are_listed(suite, monkeypatch):
    monkeypatch.setenv("DOFSPLAT_MAX_SKIPS", "1")
    monkeypatch.delenv("DOFSPLAT_REQUIRE_CUDA", raising=False)
    result = suite.runpytest("-p", "no:cacheprovider")
    result.assert_outcomes(passed=1, skipped=3)
    assert result.ret == 1
    result.stdout.fnmatch_lines(["*FAILED: skipped 2, more than DOFSPLAT_MAX_SKIPS=1:",
                                 "  test_suite.py::test_a: no tool A",
                                 "  test_suite.py::test_b: no data B",
                                 "and 1 CUDA test(s), not counted*"])


def test_cuda_skips_count_where_cuda_is_required(suite, monkeypatch):
    monkeypatch.setenv("DOFSPLAT_MAX_SKIPS", "2")
    monkeypatch.setenv("DOFSPLAT_REQUIRE_CUDA", "1")
    result = suite.runpytest("-p", "no:cacheprovider")
    assert result.ret == 1
    result.stdout.fnmatch_lines(["*FAILED: skipped 3, more than DOFSPLAT_MAX_SKIPS=2:",
                                 "  test_suite.py::test_gpu: no GPU"])


@pytest.mark.parametrize("limit", ["2", None])
def test_skips_within_the_limit_or_without_one_pass(suite, monkeypatch, limit):
    monkeypatch.delenv("DOFSPLAT_REQUIRE_CUDA", raising=False)
    if limit is None:
        monkeypatch.delenv("DOFSPLAT_MAX_SKIPS", raising=False)
    else:
        monkeypatch.setenv("DOFSPLAT_MAX_SKIPS", limit)
    result = suite.runpytest("-p", "no:cacheprovider")
    result.assert_outcomes(passed=1, skipped=3)
    assert result.ret == 0
    if limit is None:
        assert "DOFSPLAT_MAX_SKIPS" not in result.stdout.str()
    else:
        result.stdout.fnmatch_lines(["skipped 2, at most DOFSPLAT_MAX_SKIPS=2"])
