"""bench/fuzz.py's read-side families, every mutation of every kind: links and special files at the
names a reader opens, HDF5 filters and chunks (bombs, unknown filters), text of odd size and
shape, wrong-typed metrics.json, checkpoint records, NaN/Inf in calibration files and crafted clip
archives. Each ends in a result or one 'error:' line, never a traceback, and the reader's secret
(the target of a planted link) never shows in an output. The 2,000-case run, with its time and
memory, is in bench/fuzz.md."""

from __future__ import annotations

import pytest

from bench import fuzz
from bench import fuzz_families as families

RANDOM_VARIANTS = ("special_name", "filters", "text", "metrics_types")  # each picks among several: 3 seeds
CASES = [fuzz.Case(kind, m, 500 + 10 * i + r)
         for i, (kind, m) in enumerate((k, m) for k, ms in families.MUTATIONS.items() for m in ms)
         for r in range(3 if m in RANDOM_VARIANTS else 1)]


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return fuzz.make_seeds(tmp_path_factory.mktemp("fuzz_seeds"))


def test_the_families_come_in_turn_among_the_cases():
    seen = {(c.kind, c.mutation) for c in fuzz.cases(400, seed=3)}
    for kind, mutations in families.MUTATIONS.items():
        assert {m for k, m in seen if k == kind} == set(mutations), kind


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c.kind}-{c.mutation}-{c.seed}")
def test_a_read_side_case_ends_in_a_result_or_one_line(case, seeds, tmp_path):
    row = fuzz.run_case(case, seeds, tmp_path, measure_memory=False)  # the memory bound: bench/fuzz.md
    assert row["outcome"] in ("result", "one line"), row
    if case.mutation in ("link_secret", "special_name", "fifo") or case.kind == "checkpoint":
        assert row["outcome"] == "one line", row  # a planted link, FIFO or broken checkpoint is never read


def test_a_planted_secret_in_an_output_is_found(tmp_path):
    (tmp_path / "report.html").write_text("<pre>" + families.SECRET + "</pre>")
    assert families.leaked(tmp_path, [])
    assert families.leaked(tmp_path / "none", ["error: " + families.SECRET])
    (tmp_path / "report.html").write_text("<pre>nothing</pre>")
    assert not families.leaked(tmp_path, ["error: a line"])
