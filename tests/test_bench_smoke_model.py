"""The second half of the bench smoke set (tests/test_bench_smoke.py): the benches of the model, training, loading and
evaluation (``MODEL_SCRIPTS``), each run end to end at its smallest size, printing its table. A file of its own so
that ``pytest -n 2`` runs the two halves side by side; the toy data is written once for each file."""

from __future__ import annotations

import pytest

from tests.test_bench_smoke import MODEL_SCRIPTS, check_script, write_toy_data


@pytest.fixture(scope="module")
def toy_data(tmp_path_factory):
    return write_toy_data(tmp_path_factory)


@pytest.mark.slow
@pytest.mark.parametrize("script", sorted(MODEL_SCRIPTS))
def test_bench_script_runs_and_prints_its_table(script, toy_data):
    check_script(script, toy_data)
