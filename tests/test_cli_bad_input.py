"""Bad command lines get one clear error line and a non-zero exit, never a traceback, and
nothing runs: the audit's cases (negative seeds and trials, NaN or absurd numbers, an output
folder under a file) and the console script's last-resort handler."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", "osmesa")

import pytest
from typer.testing import CliRunner

from mmpa.cli import main as cli_main
from mmpa.cli.main import app

runner = CliRunner()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["run", "t", "--trial", "-1"], "--trial"),
        (["demo", "--seed", "-1"], "--seed"),
        (["navigate", "--to", "1", "--seed", "-3"], "--seed"),
        (["navigate", "--to", "1", "--timeout", "-5"], "--timeout"),
        (["navigate", "--to", "1", "--timeout", "nan"], "--timeout"),
        (["map", "export", "--resolution", "nan"], "--resolution"),
        (["map", "export", "--resolution", "0.0005"], "--resolution"),
        (["map", "export", "--resolution", "0"], "--resolution"),
        (["demo", "--set", "errors.seed=-5"], "errors.seed"),
        (["experiment", "ipe", "--seed", "-2"], "--seed"),
    ],
)
def test_bad_numbers_are_refused_before_anything_runs(tmp_path, monkeypatch, args, message) -> None:
    monkeypatch.chdir(tmp_path)  # default run folders (runs/...) would land here
    res = runner.invoke(app, args)
    assert res.exit_code == 2, res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
    assert message in res.output
    assert not (tmp_path / "runs").exists()


def test_output_folder_under_a_file_is_a_clear_error(tmp_path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("x")
    res = runner.invoke(app, ["map", "export", "--out", str(blocker / "m" / "map.yaml")])
    assert res.exit_code == 2, res.output
    assert isinstance(res.exception, SystemExit)
    assert f"{blocker} is a file" in res.output.replace("\n", "")


def test_console_script_turns_escaping_errors_into_one_line(monkeypatch, capsys) -> None:
    from mmpa.core.errors import InvalidInputError

    def raises(exc):
        def run() -> None:
            raise exc

        return run

    monkeypatch.setattr(cli_main, "app", raises(NotADirectoryError(20, "Not a directory", "/a/b")))
    with pytest.raises(SystemExit) as e:
        cli_main.main()
    assert e.value.code == 1
    assert "Not a directory: /a/b" in capsys.readouterr().out
    monkeypatch.setattr(cli_main, "app", raises(InvalidInputError("the cloud is empty")))
    with pytest.raises(SystemExit) as e:
        cli_main.main()
    assert e.value.code == 2
    assert "error: the cloud is empty" in capsys.readouterr().out
    monkeypatch.setattr(cli_main, "app", raises(RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="a bug"):  # a bug still shows its traceback
        cli_main.main()


def test_version_flag() -> None:
    from mmpa import __version__

    res = runner.invoke(app, ["--version"])
    assert res.exit_code == 0 and res.output.strip() == __version__


def test_log_level_option_turns_on_mmpa_logging() -> None:
    import logging

    log = logging.getLogger("mmpa")
    before = (log.level, list(log.handlers))
    try:
        res = runner.invoke(app, ["--log-level", "debug", "version"])
        assert res.exit_code == 0
        assert log.level == logging.DEBUG
        assert sum(getattr(h, "_mmpa", False) for h in log.handlers) == 1
        res = runner.invoke(app, ["-v", "version"])
        assert log.level == logging.INFO
        assert sum(getattr(h, "_mmpa", False) for h in log.handlers) == 1  # not added twice
        res = runner.invoke(app, ["--log-level", "chatty", "version"])
        assert res.exit_code == 2 and "unknown log level 'chatty'" in res.output
    finally:
        log.setLevel(before[0])
        log.handlers[:] = before[1]
