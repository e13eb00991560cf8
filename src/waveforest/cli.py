"""The ``waveforest`` command: one subcommand per pipeline stage (docs/design.md).

Each subcommand lives in its stage module (``waveforest.stages.<stage>``) and is loaded
lazily, so ``waveforest --help`` stays fast and a stage appears once it exists.

Errors and exit codes: every error is one line on stderr, ``waveforest: error: ...``, naming
what was typed (the option as given, e.g. ``--range``, or the file). Exit status 2 is a usage
error, something typed on the command line: an unknown command or option (with a "did you
mean" suggestion), a bad option value, a missing argument, an input file that does not exist.
Exit status 1 is bad input content: a file that exists but is wrong (a ``WaveforestError``
naming the file and the row or field), or an invalid config. Ctrl-C exits with 130, SIGTERM
with 143 and SIGHUP with 129, each after the partial outputs are removed; 0 is success.
"""

from __future__ import annotations

import ast
import atexit
import contextlib
import difflib
import importlib
import importlib.util
import os
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import click

from waveforest import __version__
from waveforest.errors import WaveforestError

# command name -> "module:attribute", in pipeline order
COMMANDS = {
    "synthesize": "waveforest.stages.synthesize:synthesize",
    "info": "waveforest.stages.info:info",
    "ingest": "waveforest.stages.ingest:ingest",
    "agc": "waveforest.stages.agc:agc",
    "calibrate": "waveforest.stages.calibrate:calibrate",
    "tune-cfd": "waveforest.stages.tune_cfd:tune_cfd_command",
    "select": "waveforest.stages.select:select",
    "vegetation": "waveforest.stages.vegetation:vegetation",
    "trace": "waveforest.stages.trace:trace",
    "simulate": "waveforest.stages.simulate:simulate",
    "features": "waveforest.stages.features:features",
    "compare": "waveforest.stages.compare:compare",
    "sensitivity": "waveforest.stages.sensitivity:sensitivity",
    "sensor-study": "waveforest.stages.sensor_study:sensor_study",
    "classify": "waveforest.stages.classify:classify",
    "diagnose": "waveforest.stages.diagnose:diagnose",
    "report": "waveforest.stages.report:report",
    "quicklook": "waveforest.stages.quicklook:quicklook",
    "survey": "waveforest.stages.survey:survey",
    "decompose": "waveforest.stages.decompose:decompose",
}


def _available(target: str) -> bool:
    return importlib.util.find_spec(target.split(":")[0]) is not None


def first_sentence(text: str) -> str:
    """The first sentence of the first paragraph of ``text``, whole, whitespace collapsed.

    A period ends the sentence when it closes the paragraph or the next word starts with a
    capital letter, so "Eq. 8", "e.g. a" and "vs. b" do not end it.
    """
    words = text.split("\f")[0].partition("\n\n")[0].split()
    if words and words[0] == "\b":  # click's no-rewrap marker
        words = words[1:]
    for i, word in enumerate(words):
        if word.endswith(".") and (i + 1 == len(words) or words[i + 1][:1].isupper()):
            return " ".join(words[: i + 1])
    return " ".join(words)


def help_line(command: click.Command) -> str:
    """A command's line in ``waveforest --help``: its ``short_help``, else the first sentence of
    its help, never shortened."""
    if command.short_help:
        return " ".join(command.short_help.split())
    return first_sentence(command.help or "")


def short_help(target: str) -> str:
    """:func:`help_line` of the command at ``target`` ("module:function"), read from the
    module's source (its ``short_help=``/``help=`` or docstring) without importing the module
    and its dependencies."""
    module, attr = target.split(":")
    tree = ast.parse(Path(importlib.util.find_spec(module).origin).read_text(encoding="utf-8"))
    fn = next(n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name == attr)
    decos = [d for d in fn.decorator_list if isinstance(d, ast.Call)
             and getattr(d.func, "attr", getattr(d.func, "id", None)) == "command"]
    given = {kw.arg: kw.value.value for d in decos for kw in d.keywords
             if kw.arg in ("help", "short_help") and isinstance(kw.value, ast.Constant)}
    given.setdefault("help", ast.get_docstring(fn, clean=False))
    return help_line(click.Command(attr, **given))


def _no_such_command(name: str, commands: list[str]) -> str:
    """The message for an unknown command ``name``, suggesting the closest of ``commands``."""
    close = difflib.get_close_matches(name, commands, n=3)
    message = f"No such command '{name}'."
    if close:
        message += " Did you mean " + " or ".join(f"'{c}'" for c in close) + "?"
    return message


class _LazyGroup(click.Group):
    def list_commands(self, ctx):
        return [name for name, target in COMMANDS.items() if _available(target)]

    def get_command(self, ctx, name):
        target = COMMANDS.get(name)
        if target is None or not _available(target):
            return None
        module, attr = target.split(":")
        return getattr(importlib.import_module(module), attr)

    def resolve_command(self, ctx, args):
        name = click.utils.make_str(args[0])
        if not ctx.resilient_parsing and not name.startswith("-") and self.get_command(ctx, name) is None:
            raise click.UsageError(_no_such_command(name, self.list_commands(ctx)), ctx)
        return super().resolve_command(ctx, args)

    def format_commands(self, ctx, formatter):  # pipeline order; no stage imported for its line
        rows = [(name, short_help(COMMANDS[name])) for name in self.list_commands(ctx)]
        if rows:
            with formatter.section("Commands (pipeline order)"):
                formatter.write_dl(rows)


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="waveforest")
def cli() -> None:
    """Simulate and analyse waveform-recording airborne LiDAR over vegetation.

    After Hovi & Korpela (2014). Each subcommand is one stage of the Snakemake
    workflow; run `waveforest STAGE --help` for its inputs and outputs.
    """


class Terminated(SystemExit):
    """Raised in the main thread on SIGTERM (or SIGHUP): unwinds the stack so that every
    ``finally:`` runs (atomic writers remove their ``.part`` files, spills are deleted), then
    exits with status 128 + the signal number, as a shell reports a death by that signal."""

    def __init__(self, signum: int):
        super().__init__(128 + signum)
        self.signum = signum


def _terminate(signum, frame) -> None:
    signal.signal(signum, signal.SIG_IGN)  # a second signal must not interrupt the clean-up
    raise Terminated(signum)


@contextlib.contextmanager
def _terminate_cleanly() -> Iterator[None]:
    """Turn SIGTERM and SIGHUP into :class:`Terminated` while the block runs (main thread only)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {sig: signal.signal(sig, _terminate) for sig in (signal.SIGTERM, signal.SIGHUP)}
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


_NO_ARGS_IS_HELP = getattr(click.exceptions, "NoArgsIsHelpError", ())
"""The usage error of a bare ``waveforest`` (click >= 8.2; older click prints the help and exits 0)."""


def _error(message: str, code: int) -> None:
    """End with ``waveforest: error: message`` on stderr and exit status ``code``."""
    click.echo(f"waveforest: error: {message}", err=True)
    sys.exit(code)


def _usage_message(exc: click.UsageError) -> str:
    """One line: click's message and where to read the command's options."""
    message = " ".join(exc.format_message().split())
    if exc.ctx is None:
        return message
    return f"{message} (see '{exc.ctx.command_path} --help')"


def main(argv: list[str] | None = None) -> None:
    """Entry point: every error is one line ``waveforest: error: ...`` on stderr; exit 2 for a
    usage error, 1 for bad input content (module docstring).

    Ctrl-C exits with 130, SIGTERM with 143 and SIGHUP with 129, each after the partial
    outputs are removed.
    """
    try:
        with _terminate_cleanly():
            cli.main(args=argv, prog_name="waveforest", standalone_mode=False)
    except WaveforestError as exc:
        _error(str(exc), 1)
    except Terminated as exc:
        click.echo(f"waveforest: terminated by signal {signal.Signals(exc.signum).name}; partial outputs removed", err=True)
        sys.exit(exc.code)
    except click.exceptions.Abort:
        click.echo("waveforest: interrupted; partial outputs removed", err=True)
        sys.exit(130)
    except _NO_ARGS_IS_HELP as exc:  # bare ``waveforest``: the help on stderr, as click shows it
        exc.show()
        sys.exit(exc.exit_code)
    except click.UsageError as exc:
        _error(_usage_message(exc), 2)
    except click.ClickException as exc:
        _error(" ".join(exc.format_message().split()), exc.exit_code)
    except click.exceptions.Exit as exc:
        sys.exit(exc.exit_code)


def entry() -> None:
    """Console-script entry point: :func:`main`, then an exit without the interpreter's teardown.

    After the command, stdout and stderr are flushed and the ``atexit`` handlers run, as at
    any exit; then ``os._exit`` ends the process with main's exit code. That skips the
    finalisation of every loaded module (Numba's and LLVM's clean-up is a large share of a
    short command: docs/validation.md, "The commands side by side"). While another
    non-daemon thread is alive the exit is the normal one.
    """
    try:
        main()
        code = 0
    except SystemExit as exc:
        code = exc.code
    if any(t.is_alive() and not t.daemon for t in threading.enumerate() if t is not threading.current_thread()):
        sys.exit(code)
    if code is None:
        code = 0
    elif not isinstance(code, int):  # sys.exit("message"): printed, status 1
        print(code, file=sys.stderr)
        code = 1
    try:
        sys.stdout.flush()
        sys.stderr.flush()
    except OSError:  # a closed pipe: nothing left to say
        pass
    atexit._run_exitfuncs()  # what the interpreter's own exit runs first
    os._exit(code)


if __name__ == "__main__":  # pragma: no cover
    entry()
