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
