"""The one helper every pacdp-* command reports errors through."""

import errno

import pytest

from lerobot_pacdp.cli_errors import UserInputError, report_user_errors


def fails_with(exc: BaseException):
    def body() -> int:
        raise exc

    return body


@pytest.mark.parametrize(
    ("exc", "line", "status"),
    [
        (UserInputError("--x=3 is too big; pass 2."), "prog: error: --x=3 is too big; pass 2.", 2),
        (OSError(errno.EROFS, "Read-only file system", "/data/out"),
         "prog: error: Read-only file system (/data/out); check that path's permissions, or write somewhere else.", 2),
        (OSError(errno.EDQUOT, "Disk quota exceeded"), "prog: error: no space left on the device; free some space "
         "and run the command again.", 2),
        (KeyboardInterrupt(), "prog: error: interrupted; nothing was written.", 130),
    ],
)  # fmt: skip
def test_user_errors_become_one_line_and_an_exit_status(capsys, exc, line, status):
    assert report_user_errors("prog", fails_with(exc)) == status
    assert capsys.readouterr().err == line + "\n"


def test_an_unexpected_error_keeps_its_traceback():
    with pytest.raises(OSError, match="Input/output error"):
        report_user_errors("prog", fails_with(OSError(errno.EIO, "Input/output error")))
    with pytest.raises(RuntimeError):
        report_user_errors("prog", fails_with(RuntimeError("a bug")))


def test_argparse_spellings_become_draccus_ones():
    from lerobot_pacdp.cli_errors import draccus_spelling

    argv = ["--output-root", "out", "--overwrite", "--episodes=0-3", "--zarr", "x.zarr", "--help"]
    assert draccus_spelling(argv) == ["--output_root=out", "--overwrite=true", "--episodes=0-3", "--zarr=x.zarr", "--help"]


def test_every_command_parses_flags_and_lists_alike_and_a_bad_list_names_the_syntax(capsys):
    from dataclasses import dataclass, field
    from pathlib import Path

    from lerobot_pacdp.cli_errors import run_draccus_cli

    @dataclass
    class Options:
        runs: list[Path] = field(default_factory=list)
        overwrite: bool = False

    seen = []
    assert run_draccus_cli("prog", Options, lambda cfg: seen.append(cfg) or 0, ["--runs=[a,b]", "--overwrite"]) == 0
    assert seen == [Options(runs=[Path("a"), Path("b")], overwrite=True)]
    assert run_draccus_cli("prog", Options, lambda cfg: 0, ["--runs=a,b"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("prog: error: ") and len(err.splitlines()) == 1
    assert "Write a list in brackets, as LeRobot's CLIs do: --flag=[a,b] (one item: --flag=[a])." in err
