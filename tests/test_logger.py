"""RunLogger's discard after bad input: its own new event file goes, an older one (a resumed run's) stays."""

from l3d_app.runtime.logger import RunLogger


def test_discard_removes_only_this_loggers_event_file_when_it_logged_only_the_config(tmp_path):
    old = tmp_path / "events.out.tfevents.1.host.1.0"
    old.write_bytes(b"resumed run")
    log = RunLogger(tmp_path)
    log.text("config", "```\na: 1\n```")
    assert len(list(tmp_path.glob("events.out.tfevents.*"))) == 2
    assert log.discard_if_at_most(1) is True
    assert list(tmp_path.glob("events.out.tfevents.*")) == [old] and old.read_bytes() == b"resumed run"


def test_discard_keeps_a_run_that_logged_more(tmp_path):
    log = RunLogger(tmp_path)
    log.text("config", "x")
    log.scalar("loss", 0.5, 0)
    assert log.records == 2
    assert log.discard_if_at_most(1) is False
    log.close()
    assert len(list(tmp_path.glob("events.out.tfevents.*"))) == 1
