"""The suite's disk use stays bounded (tests/conftest.py, "Disk"): a passed test's tmp_path goes at once, a module-
or session-scoped fixture's folders go when the fixture is torn down, a failed test's folder stays for a look. Run
in an inner pytest session on the suite's own conftest.py, with a fixture nested in another (the inner one's folder
belongs to the inner fixture, not to the one that set it up)."""

from pathlib import Path

pytest_plugins = ["pytester"]

CONFTEST = (Path(__file__).parent / "conftest.py").read_text()

SHARED = '''

@pytest.fixture(scope="session")
def shared(tmp_path_factory):
    return tmp_path_factory.mktemp("session_data")
'''

FIRST_MODULE = '''
import pytest


@pytest.fixture(scope="module")
def data(shared, tmp_path_factory):  # sets up the session fixture first, inside its own set-up
    out = tmp_path_factory.mktemp("module_data")
    (out / "x").write_text("1")
    return out


def test_uses(data, tmp_path):
    (tmp_path / "y").write_text("1")
    assert data.exists()


def test_fails(tmp_path):
    (tmp_path / "kept").write_text("1")
    assert False
'''

SECOND_MODULE = '''
def test_after(shared, tmp_path_factory):
    names = {p.name for p in tmp_path_factory.getbasetemp().iterdir() if p.is_dir() and not p.is_symlink()}
    assert not any(n.startswith("module_data") for n in names), names  # its module ended
    assert any(n.startswith("session_data") for n in names), names  # alive until the session ends
    assert not any(n.startswith("test_uses") for n in names), names
    assert any(n.startswith("test_fails") for n in names), names
'''


def _run(pytester, *args, conftest=CONFTEST):
    # the project's layout: the ini at the root, conftest.py beside the tests in tests/ (a conftest's own hooks see
    # only the nodes under its folder, and the session, which tears down session fixtures, is not one of them)
    tests = pytester.path / "tests"
    tests.mkdir(exist_ok=True)
    for name, text in {"conftest.py": conftest + SHARED, "test_a.py": FIRST_MODULE, "test_b.py": SECOND_MODULE}.items():
        (tests / name).write_text(text)
    pytester.makeini("[pytest]\ntmp_path_retention_policy = failed\ntestpaths = tests\n")
    base = pytester.path / "base"
    result = pytester.runpytest_inprocess("-p", "no:cacheprovider", f"--basetemp={base}", *args)
    left = {p.name.rstrip("0123456789") for p in base.iterdir() if p.is_dir() and not p.is_symlink()}
    return result, left


def test_fixture_folders_go_when_the_fixture_ends_and_a_failed_tests_folder_stays(pytester):
    result, left = _run(pytester)
    result.assert_outcomes(passed=2, failed=1)
    assert left == {"test_fails"}  # the session fixture's folder went when the session tore it down


def test_retention_all_keeps_everything(pytester):
    result, left = _run(pytester, "-o", "tmp_path_retention_policy=all")
    result.assert_outcomes(passed=1, failed=2)  # test_after sees the module's folder kept
    assert left == {"module_data", "session_data", "test_uses", "test_fails"}


def test_the_header_says_how_much_disk_is_free(pytester):
    result, _ = _run(pytester)
    result.stdout.fnmatch_lines(["disk: * GiB free in *base (the slow tier needs about * GiB at once)"])


def test_a_short_disk_is_said_also_under_q(pytester):
    assert "\nNEEDED_GIB = 3\n" in CONFTEST
    result, _ = _run(pytester, "-q", conftest=CONFTEST.replace("\nNEEDED_GIB = 3\n", "\nNEEDED_GIB = 10**9\n"))
    result.stdout.fnmatch_lines(["disk: only * GiB free in *base (the slow tier needs about 1000000000 GiB at once)"])
    result, _ = _run(pytester, "-q")
    assert "disk:" not in result.stdout.str()
