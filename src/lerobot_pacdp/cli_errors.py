"""How a bad input reaches a user: one line naming the problem and the fix, never a traceback.

`UserInputError` is the one base class of this package's user-facing errors; `run_draccus_cli` parses the
flags of every `pacdp-*` command, and `report_user_errors` is the one place such a command turns that error
(and a full disk, a denied write, Ctrl-C) into one line and an exit status. `name_plugin_config_errors` does the same for LeRobot's own CLIs (lerobot-train,
lerobot-eval), whose config parser, draccus, replaces the message of any error raised while building a
config with "Couldn't instantiate class PacdpConfig using the given arguments".
"""

import errno
import functools
import sys
from collections.abc import Callable, Sequence

EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = 130  # the shell's status for a command stopped by SIGINT
_PACKAGE = __name__.rpartition(".")[0]


class UserInputError(ValueError):
    """A problem the user can fix (a flag, a file, a directory); the message names it and the fix."""


def _os_error_line(exc: OSError) -> str | None:
    """One line for the OS errors a user fixes outside the program (space, permissions), else None."""
    where = f" ({exc.filename})" if exc.filename else ""
    if exc.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"no space left on the device{where}; free some space and run the command again."
    if exc.errno in (errno.EACCES, errno.EPERM, errno.EROFS):
        return f"{exc.strerror}{where}; check that path's permissions, or write somewhere else."
    return None


def report_user_errors(prog: str, body: Callable[[], int]) -> int:
    """Run a command's body; a `UserInputError`, a full disk or a denied write becomes `prog: error: ...`
    and exit 2, Ctrl-C a one-line notice and 130. The commands stage every output (`atomic_io`), so
    none of these leaves anything behind."""
    try:
        return body()
    except UserInputError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except OSError as exc:
        line = _os_error_line(exc)
        if line is None:
            raise
        print(f"{prog}: error: {line}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:
        print(f"{prog}: error: interrupted; nothing was written.", file=sys.stderr)
        return EXIT_INTERRUPTED


def draccus_spelling(argv: Sequence[str]) -> list[str]:
    """`argv` with argparse spellings turned into draccus' (`--output-root X` -> `--output_root=X`, a bare
    `--overwrite` -> `--overwrite=true`), so the converters' old command lines keep working."""
    args, spelled = list(argv), []
    while args:
        arg = args.pop(0)
        if not arg.startswith("--") or arg == "--help":
            spelled.append(arg)
            continue
        name, has_value, value = arg[2:].partition("=")
        if not has_value:
            value = args.pop(0) if args and not args[0].startswith("--") else "true"
        spelled.append(f"--{name.replace('-', '_')}={value}")
    return spelled


def run_draccus_cli[T](prog: str, config_class: type[T], body: Callable[[T], int], argv: Sequence[str] | None) -> int:
    """Parse `argv` into `config_class` with draccus (the flag style of LeRobot's own CLIs: `--flag=value`,
    lists as `--flag=[a,b]`), run `body` on it, and report errors as `report_user_errors` does; a flag
    draccus cannot decode is one too."""
    import draccus
    from draccus.utils import ParsingError

    def parse_and_run() -> int:
        args = draccus_spelling(sys.argv[1:] if argv is None else argv)
        try:
            cfg = draccus.parse(config_class, args=args, prog=prog)
        except ParsingError as exc:
            message = str(exc).replace("\n", " ")
            if "valid input for a list type" in message:
                message += " Write a list in brackets, as LeRobot's CLIs do: --flag=[a,b] (one item: --flag=[a])."
            raise UserInputError(message) from None
        return body(cfg)

    return report_user_errors(prog, parse_and_run)


# ----------------------------------------------------------------------------------------------------------
# LeRobot's CLIs
def raised_in_this_package(exc: BaseException) -> bool:
    """True if `exc` was raised in (or passed through) this package's code."""
    tb = exc.__traceback__
    while tb is not None:
        if tb.tb_frame.f_globals.get("__name__", "").startswith(f"{_PACKAGE}."):
            return True
        tb = tb.tb_next
    return False


def plugin_config_error(exc: BaseException) -> Exception | None:
    """The error behind a draccus failure if it was raised while building one of this package's configs
    (`PacdpConfig`, `RobomimicEnvConfig`, including the LeRobot checks they call), else None."""
    from draccus.utils import DraccusException

    cause = exc.__cause__
    while cause is not None:
        if isinstance(cause, (ValueError, TypeError)) and not isinstance(cause, DraccusException):
            return cause if raised_in_this_package(cause) else None
        cause = cause.__cause__
    return None


def name_plugin_config_errors() -> None:
    """Make LeRobot's CLIs print this package's config errors as they are written, on one line.

    draccus turns a ValueError from a config's `__post_init__` into a generic ParsingError (and, for
    `--policy.*` and `--env.*`, wraps that in "Could not decode the value into any of the given types").
    LeRobot prints a DecodingError as `error: ...` and exits 1, but lets a bare ParsingError (`--env.*`
    of lerobot-eval) escape as a traceback. So `draccus.parse`, which every LeRobot config loader calls,
    is wrapped: a failure whose cause was raised by this package's configs is re-raised as a
    DecodingError carrying that cause's message; every other error passes through untouched.
    Idempotent; called when the plugin is imported.
    """
    import draccus
    from draccus.utils import DecodingError, ParsingError

    if getattr(draccus.parse, "_names_plugin_config_errors", False):
        return
    parse = draccus.parse

    @functools.wraps(parse)
    def parse_naming_plugin_errors(*args, **kwargs):
        try:
            return parse(*args, **kwargs)
        except ParsingError as exc:
            cause = plugin_config_error(exc)
            if cause is None:
                raise
            key_path = exc.key_path if isinstance(exc, DecodingError) else ()
            raise DecodingError(key_path, str(cause)) from cause

    parse_naming_plugin_errors._names_plugin_config_errors = True
    draccus.parse = parse_naming_plugin_errors
