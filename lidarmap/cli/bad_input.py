"""One place that turns known errors into one line on stderr and exit code 2 (bad input).

Known: the engine's errors (SlamEngineError: bad log, bad config, bad trajectory file...), missing or
unreadable files, malformed YAML/JSON config files. ``--verbose`` prints the traceback first.
Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations

import contextlib
import json
import traceback
from collections.abc import Iterator

import typer

from slam_engine.errors import SlamEngineError

BAD_INPUT_EXIT_CODE = 2


def known_errors() -> tuple[type[BaseException], ...]:
    """The errors reported as bad input. pydantic and PyYAML are imported here, once an error is
    caught, not when the command line starts (``lidarmap --help`` needs neither)."""
    import yaml
    from pydantic import ValidationError

    return SlamEngineError, OSError, ValidationError, yaml.YAMLError, json.JSONDecodeError


def one_line(error: BaseException) -> str:
    """A one-line description of a known error: what is wrong and where."""
    from pydantic import ValidationError

    if isinstance(error, OSError) and error.filename is not None:
        text = f"{error.filename}: {error.strerror or error}"
    elif isinstance(error, ValidationError):
        text = "; ".join(f"{'.'.join(str(p) for p in e['loc']) or 'value'}: {e['msg']}" for e in error.errors())
    else:
        text = str(error) or type(error).__name__
    return " ".join(text.split())


@contextlib.contextmanager
def bad_input_exits(verbose: bool = False) -> Iterator[None]:
    """Wrap a command's body: known errors -> ``error: ...`` on stderr and exit code 2."""
    try:
        yield
    except Exception as error:
        if not isinstance(error, known_errors()):
            raise
        if verbose:
            traceback.print_exc()
        typer.echo(f"error: {one_line(error)}", err=True)
        raise typer.Exit(BAD_INPUT_EXIT_CODE) from None
