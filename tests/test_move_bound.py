"""benchmarks/move_bound.py: CEM at several budgets on the comparison's episodes, resumable episode by episode."""
import json

import pytest

from benchmarks import move_bound


def test_budgets_play_the_same_episodes_and_a_rerun_resumes(tmp_path, capsys):
    argv = ["--out", str(tmp_path), "--seeds", "0", "--episodes", "2", "--budgets", "1x8x1", "2x8x1",
            "--max-steps", "2", "--no-progress"]
    assert move_bound.main(argv) == 0
    rows = [json.loads(x) for x in (tmp_path / "episodes.jsonl").read_text().splitlines()]
    assert len(rows) == 4
    by = {}
    for r in rows:
        by.setdefault(r["seed"], set()).add((round(r["start_error"], 12), r["target_name"]))
    assert sorted(by) == [10000, 10001] and all(len(v) == 1 for v in by.values())   # one episode, every budget
    summary = json.loads((tmp_path / "results.json").read_text())["summary"]
    assert {s["budget"] for s in summary} == {"1x8x1", "2x8x1"}
    one = next(s for s in summary if s["budget"] == "1x8x1")
    moves = sum(r["steps"] for r in rows if r["budget"] == "1x8x1")
    assert one["sim_evals_per_move"] == pytest.approx(8 * 1 * 1)                      # H x candidates x iterations
    assert moves >= 2
    assert move_bound.main(argv) == 0                                                   # all done: nothing reruns
    assert len((tmp_path / "episodes.jsonl").read_text().splitlines()) == 4
    assert json.loads((tmp_path / "results.json").read_text())["complete"]
    more = [*argv[:argv.index("--budgets")], "--budgets", "1x8x1", "3x8x1", *argv[argv.index("--max-steps"):]]
    assert move_bound.main([*more, "--summary-only"]) == 0                              # runs nothing
    res = json.loads((tmp_path / "results.json").read_text())
    assert not res["complete"] and {s["budget"] for s in res["summary"]} == {"1x8x1"}
    assert len((tmp_path / "episodes.jsonl").read_text().splitlines()) == 4
    with pytest.raises(SystemExit):
        move_bound.main(["--out", str(tmp_path), "--budgets", "2x300"])
    assert "HORIZONxCANDIDATESxITERATIONS" in capsys.readouterr().err
