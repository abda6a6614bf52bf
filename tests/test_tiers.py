"""The two test tiers stay honest (docs/development.md, "Test tiers"): conftest.py refuses a test outside the slow
tier that uses a fixture writing a toy dataset or building a store, whether it names the fixture as an argument
(at collection) or asks for it by name at run time. Run on small test files in pytester's own folder, with this
suite's conftest.py; the refused fixtures are never built."""

from __future__ import annotations

from pathlib import Path

import pytest

pytest_plugins = ["pytester"]

CONFTEST = (Path(__file__).parent / "conftest.py").read_text()
PYPROJECT = (Path(__file__).parents[1] / "pyproject.toml").read_text()


@pytest.fixture
def suite(pytester):
    pytester.makeconftest(CONFTEST)
    pytester.makepyprojecttoml(PYPROJECT[PYPROJECT.index("[tool.pytest.ini_options]"):].replace(
        'testpaths = ["tests"]', ""))
    return pytester


def test_an_unmarked_test_using_a_store_fixture_is_refused_at_collection(suite):
    suite.makepyfile(test_a="def test_reads(tiny_store):\n    pass\n\ndef test_plain():\n    pass\n")
    result = suite.runpytest_inprocess("--collect-only", "-q")
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(["*must be marked @pytest.mark.slow*", "*test_a.py::test_reads uses *tiny_store*"])


def test_a_fixture_built_on_a_store_fixture_is_refused_too(suite):
    suite.makepyfile(test_b="import pytest\n\n@pytest.fixture\ndef rows(ho3d_small_eval_store):\n    return 1\n\n"
                            "def test_rows(rows):\n    pass\n")
    result = suite.runpytest_inprocess("--collect-only", "-q")
    assert result.ret == pytest.ExitCode.USAGE_ERROR
    result.stderr.fnmatch_lines(["*test_b.py::test_rows uses *ho3d_small_eval_store*"])


def test_a_store_fixture_asked_for_by_name_fails_the_test_before_it_is_built(suite):
    suite.makepyfile(test_c="def test_by_name(request):\n    request.getfixturevalue('dexycb_s0')\n\n"
                            "def test_probe(tmp_path_factory):\n    tmp_path_factory.mktemp('probe')\n")
    base = suite.path.parent / "basetemp"
    result = suite.runpytest_inprocess("-q", f"--basetemp={base}")
    result.assert_outcomes(failed=1, passed=1)
    result.stdout.fnmatch_lines(["*test_c.py::test_by_name uses dexycb_s0: mark it @pytest.mark.slow*"])
    made = [p.name for p in base.iterdir()]
    assert "probe0" in made and not [name for name in made if name.startswith("dexycb_s0")], made


def test_marked_tests_and_plain_ones_are_collected_and_the_marker_is_strict(suite):
    suite.makepyfile(test_d="import pytest\n\n@pytest.mark.slow\ndef test_reads(tiny_store):\n    pass\n\n"
                            "def test_plain(mano_dir):\n    pass\n")
    result = suite.runpytest_inprocess("--collect-only", "-q", "-m", "not slow")
    assert result.ret == pytest.ExitCode.OK
    result.stdout.fnmatch_lines(["*test_d.py::test_plain*", "*1/2 tests collected (1 deselected)*"])
    suite.makepyfile(test_e="import pytest\n\n@pytest.mark.slw\ndef test_typo():\n    pass\n")
    assert suite.runpytest_inprocess("--collect-only", "-q", "test_e.py").ret != pytest.ExitCode.OK
