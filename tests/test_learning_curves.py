"""benchmarks.studies.learning_curves: the per-step table across runs, and its refusals."""
import pytest

from benchmarks.studies import learning_curves


def write_eval(folder, rows):
    folder.mkdir()
    lines = ["step,success_rate,mean_reward,mean_length,mean_final_error"]
    lines += [f"{s},{su},0.0,{ln},{fe}" for s, su, ln, fe in rows]
    (folder / "eval.csv").write_text("\n".join(lines) + "\n")
    return folder


def test_curves_keep_the_steps_every_run_has_and_average_them(tmp_path):
    a = write_eval(tmp_path / "a", [(1000, 0.5, 60, 0.02), (2000, 1.0, 20, 0.009)])
    b = write_eval(tmp_path / "b", [(1000, 0.0, 100, 0.04), (2000, 0.9, 30, 0.01), (3000, 1.0, 15, 0.008)])
    steps, c = learning_curves.curves([a, b])
    assert steps == [1000, 2000]
    assert c["success_rate"].mean(0).tolist() == pytest.approx([0.25, 0.95])
    assert c["mean_length"][:, 1].tolist() == [20, 30]


def test_main_prints_a_row_per_step_and_refuses_to_replace_a_figure(tmp_path, capsys):
    a = write_eval(tmp_path / "a", [(1000, 0.5, 60, 0.02)])
    assert learning_curves.main([str(a)]) == 0
    assert "| 1000 | 0.50; 0.50-0.50 | 60.0; 60.0-60.0 | 2.00 |" in capsys.readouterr().out
    fig = tmp_path / "fig.png"
    fig.write_bytes(b"mine")
    with pytest.raises(SystemExit):
        learning_curves.main([str(a), "--out", str(fig)])
    assert fig.read_bytes() == b"mine"


def test_a_folder_without_eval_csv_is_named(tmp_path):
    with pytest.raises(SystemExit, match="no eval.csv"):
        learning_curves.curves([tmp_path])
