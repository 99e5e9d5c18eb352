from training.summarize import main, summarize_run


def test_summary_means_of_first_and_last_tenth(tmp_path, capsys):
    run = tmp_path / "stage9"
    run.mkdir()
    lines = ["step,epoch,skipped,lr,grad_norm,seconds,loss,photo"]
    lines += [f"{i},0,0,0.1,1.0,0.5,{100 - i},{i}" for i in range(1, 21)]
    lines.insert(5, "4,0,1,,,,nan,")  # a skipped step is counted, not averaged
    (run / "metrics.csv").write_text("\n".join(lines) + "\n")
    s = summarize_run(run)
    assert s["steps"] == 20 and s["skipped"] == 1 and s["seconds"] == 10.0
    assert s["losses"]["loss"] == (98.5, 80.5)  # steps 1-2 and 19-20
    assert s["losses"]["photo"] == (1.5, 19.5)
    assert main([str(run)]) == 0 and "stage9 | 20 | 10 |" in capsys.readouterr().out
