"""Issue 42, deliverable 8: a quick sample of bench/fuzz.py's mutated bundles, recon folders and
captures to import (issue 81).

Every case (truncation, bit flips, huge declared shapes, wrong dtypes, NaN/Inf, odd strings and
numbers, dropped objects, links and external storage, a mutated metrics.json) must end in a
result or one 'error:' line: no traceback, within the time limit. The benchmark runs 1,200 such
cases and also holds each under 1 GiB of peak memory (bench/fuzz.md)."""

from __future__ import annotations

import pytest

from bench import fuzz

CASES = fuzz.cases(48, seed=42)


@pytest.fixture(scope="module")
def seeds(tmp_path_factory):
    return fuzz.make_seeds(tmp_path_factory.mktemp("fuzz_seeds"))


def test_the_sample_covers_every_mutation_of_every_kind():
    seen = {(c.kind, c.mutation) for c in CASES}
    assert {m for k, m in seen if k == "bundle"} == set(fuzz.BUNDLE_MUTATIONS)
    assert {m for k, m in seen if k == "recon"} == set(fuzz.RECON_MUTATIONS)
    assert {m for k, m in seen if k == "import"} == set(fuzz.IMPORT_MUTATIONS)


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"{c.kind}-{c.mutation}-{c.seed}")
def test_a_mutated_file_ends_in_a_result_or_one_line(case, seeds, tmp_path):
    row = fuzz.run_case(case, seeds, tmp_path, measure_memory=False)  # the memory bound: bench/fuzz.md
    assert row["outcome"] in ("result", "one line"), row


def test_the_harness_calls_a_traceback_failed():
    class Res:
        output, exit_code, exception = "Traceback (most recent call last):\n  ...", 1, ValueError("x")

    assert fuzz._outcome(Res())[0] == "FAILED"

    class Two:
        output, exit_code, exception = "error: a\nerror: b\n", 2, SystemExit(2)

    assert fuzz._outcome(Two())[0] == "FAILED"
