"""benchmarks.loaded_machine: the load really is other sessions' busy processes, and the table compares each
learner-thread setting with the default under the same load (the training runs are replaced by a stand-in)."""
import os

from benchmarks import loaded_machine


def test_hogs_run_in_their_own_session_and_are_stopped():
    hogs = loaded_machine.start_hogs(2)
    try:
        assert all(os.getsid(h.pid) == h.pid != os.getsid(0) for h in hogs)  # each leads a new session
        assert all(h.poll() is None for h in hogs)
    finally:
        loaded_machine.stop_hogs(hogs)
    assert all(h.returncode is not None for h in hogs)


def test_thread_settings():
    assert loaded_machine.learner_threads_value("all") == os.cpu_count()
    assert loaded_machine.learner_threads_value("0") == 0 and loaded_machine.learner_threads_value("3") == 3


def test_table_has_a_row_per_load_and_setting_with_ratios_to_the_default(monkeypatch, capsys):
    loads = []

    def stand_in(run_root, name, seconds, threads):
        loads.append((name, threads))
        rate = {"quiet_0": 1000.0, "quiet_all": 800.0, "loaded_0": 500.0, "loaded_all": 100.0}[name]
        return {"agent_steps": int(rate * seconds), "elapsed_s": seconds, "agent_steps_per_s": rate}

    monkeypatch.setattr(loaded_machine, "train_for", stand_in)
    assert loaded_machine.main(["--seconds", "2", "--hogs", "1", "--no-append"]) == 0
    assert loads == [("quiet_0", 0), ("quiet_all", os.cpu_count()), ("loaded_0", 0), ("loaded_all", os.cpu_count())]
    out = capsys.readouterr().out
    assert f"| loaded | all ({os.cpu_count()}) | 200 | 100 | 0.20 |" in out
    assert "| quiet | 0 (0) | 2,000 | 1,000 | 1.00 |" in out and "| quiet | all" in out and "0.80 |" in out


def test_bad_thread_settings_are_a_usage_error(capsys):
    import pytest
    with pytest.raises(SystemExit) as exit_info:
        loaded_machine.main(["--threads", "two", "--no-append"])
    assert exit_info.value.code == 2 and "--threads" in capsys.readouterr().err
