"""The ``jaxland`` command: ``config``, ``simulate``, ``montecarlo``, ``fit``, ``predict``,
``design``. (The benchmarks are scripts in the repository's ``benchmarks/`` folder, not part
of the installed package.)

Exit codes: 0 success, 2 invalid input (the message names field, value and rule), 3 numerical
failure of the integration. Compiled programs are kept on disk between runs
(``_common.use_compilation_cache``).
"""

from __future__ import annotations

import argparse
import re
import sys

from .._errors import ConfigError, SimulationError
from .._solvers import METHODS, Impulse, Tsit5
from ._montecarlo import cmd_montecarlo
from ._simulate import cmd_config, cmd_simulate

EXIT_INVALID = 2
EXIT_NUMERICAL = 3
EXIT_SIGNAL = 128  # + the signal's number: a command a signal stopped (130: Ctrl-C)
EXIT_OS = 1  # writing failed (the system's error, named)


class _Parser(argparse.ArgumentParser):
    """Bad input is one line (field, value, rule) and exit 2: argparse's own errors too,
    without the usage block in front (``--help`` has it)."""

    def error(self, message):
        self.exit(EXIT_INVALID, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="jaxland", description="jaxland: landings of a legged vehicle on crushable "
        "honeycomb gear (quarter and full 3-D models), Monte Carlo, calibration, design.")
    from .. import __version__

    p.add_argument("--version", action="version", version=f"jaxland {__version__}")
    sub = p.add_subparsers(dest="command", required=True)

    c = sub.add_parser("config", help="print the vehicle configuration (default: the paper's) "
                                      "as commented TOML")
    c.add_argument("--config", help="a vehicle TOML to validate and print in full")
    c.set_defaults(func=cmd_config)

    s = sub.add_parser("simulate", help="simulate one landing, write CSV, summary and figures")
    s.add_argument("--config", help="vehicle TOML (default: the paper's vehicle)")
    s.add_argument("--scene", help="scene TOML ([scene] table, keys as the flags below with "
                                   "their units, e.g. roll_deg = 3; a touchdown speed is "
                                   "sink_speed_mps with drop_height_m = 0; also mass_scale and "
                                   "com_offset_m, which have no flag); flags override it")
    s.add_argument("--model", default="auto", choices=("auto", "quarter", "full"),
                   help="auto (default): the smallest model that represents the scene exactly")
    s.add_argument("--drop-height", type=float,
                   help="clearance of the lowest foot at release [m] (default 0.2; on a "
                        "slope along the ground's normal)")
    s.add_argument("--sink-speed", type=float, help="downward speed at release [m/s] (default 0)")
    s.add_argument("--touchdown-speed", type=float,
                   help="start at touchdown with this downward speed [m/s]")
    s.add_argument("--horizontal-speed", type=float,
                   help="horizontal speed [m/s] (default 0)")
    s.add_argument("--heading-deg", type=float,
                   help="direction of the horizontal speed [deg] (default 0)")
    for ax in ("roll", "pitch", "yaw"):
        s.add_argument(f"--{ax}-deg", type=float, help=f"body {ax} at release [deg] (default 0)")
        s.add_argument(f"--{ax}-rate-degps", type=float,
                       help=f"body {ax} rate [deg/s] (default 0)")
    s.add_argument("--slope-deg", type=float, help="ground slope [deg] (default 0)")
    s.add_argument("--slope-direction-deg", type=float,
                   help="downhill direction [deg] (default 0)")
    s.add_argument("--friction", type=float,
                   help="foot-ground friction mu [-] (default: the vehicle's ground.mu)")
    s.add_argument("--plateau-scale", type=float, nargs="+",
                   help="honeycomb plateau-force scale per leg (scatter), one value per leg "
                        "[-] (default 1 on every leg)")
    s.add_argument("--method", default="euler", choices=METHODS,
                   help="integrator (default euler; see docs/integrators.md)")
    s.add_argument("--dt", type=float, default=None,
                   help="integration step [s] (default 1e-5, or half the method's stability "
                        "limit for this vehicle if smaller; impulse: the step cap; tsit5: the "
                        "first step)")
    s.add_argument("--impulse", type=float, help="impulse step dI of --method impulse [N s] "
                   f"(default {Impulse().dI:g})")
    s.add_argument("--rtol", type=float, help="relative tolerance of --method tsit5 [-] "
                   f"(default {Tsit5().rtol:g})")
    s.add_argument("--atol", type=float, help="absolute tolerance of --method tsit5 [state "
                   f"units: m, m/s] (default {Tsit5().atol:g})")
    s.add_argument("--max-steps", type=int, help="step budget of --method tsit5 "
                   f"(default {Tsit5().max_steps})")
    s.add_argument("--t-end", type=float, default=1.2, help="simulated time [s] (default 1.2)")
    s.add_argument("--save-dt", type=float, default=None,
                   help="output sample interval [s] (default: the smallest whole multiple "
                        "of dt that is at least 1e-4 s; one given must divide --t-end)")
    s.add_argument("--out", default="out/simulate", help="output folder (default out/simulate)")
    s.add_argument("--no-plots", action="store_true", help="skip the figures")
    s.set_defaults(func=cmd_simulate)

    m = sub.add_parser("montecarlo", help="dispersed landings: tip-over and bottoming "
                                          "probabilities, envelopes, sensitivities")
    m.add_argument("spec", help="Monte Carlo spec TOML ([montecarlo], [dispersion.*], [fixed])")
    m.add_argument("--n", type=int, help="number of landings (overrides the spec)")
    m.add_argument("--seed", type=int, help="random seed (overrides the spec)")
    m.add_argument("--chunk", type=int, help="landings per compiled batch (bounds memory; "
                   "default 64 3-D or 512 quarter landings on a CPU, 131072 on a GPU; "
                   "rounded up to a multiple of the devices, as summary.json's chunk records)")
    m.add_argument("--config", help="vehicle TOML (default: the paper's vehicle)")
    m.add_argument("--out", default="out/montecarlo",
                   help="output folder (default out/montecarlo)")
    m.add_argument("--no-plots", action="store_true", help="skip the figures")
    m.add_argument("--quiet", action="store_true", help="no progress line")
    m.add_argument("--coordinator", metavar="HOST:PORT",
                   help="run as one of --num-processes processes (jax.distributed; process 0 "
                        "listens on HOST:PORT and writes the outputs)")
    m.add_argument("--num-processes", type=int, default=None,
                   help="processes in the run (with --coordinator)")
    m.add_argument("--process-id", type=int, default=None,
                   help="this process, 0 .. N-1 (with --coordinator)")
    m.add_argument("--devices", type=int, default=None,
                   help="CPU devices to shard each chunk over (default: one per core; a GPU "
                        "run uses its GPUs)")
    m.set_defaults(func=cmd_montecarlo)

    # calibration (`fit`, `predict`) lives in its own package, built on jaxland's public API
    from calibration.cli import add_subcommands

    add_subcommands(sub)

    from ._design import add_subcommands as add_design  # `design`: gear design

    add_design(sub)

    return p


# a negative number in scientific notation, which argparse takes for an option name
_NEGATIVE_SCI = re.compile(r"^-(\d+\.?\d*|\.\d+)[eE][+-]?\d+$")


def _join_negative_values(argv: list[str]) -> list[str]:
    """``--dt -1e-5`` as ``--dt=-1e-5``, so that the value reaches its rule's check."""
    out: list[str] = []
    for tok in argv:
        if out and _NEGATIVE_SCI.match(tok) and out[-1].startswith("--") and "=" not in out[-1]:
            out[-1] = f"{out[-1]}={tok}"
        else:
            out.append(tok)
    return out


def _refuse_empty_paths(args) -> None:
    """An empty file flag (an unset shell variable: --config "$VEHICLE") is refused, not taken
    as no flag, which would run the paper's vehicle or the default scene instead."""
    for name in ("config", "scene"):
        if getattr(args, name, None) == "":
            raise ConfigError(f"--{name}", "", "is empty: give a file, or leave the flag out")
    # an empty path reads as the current folder ('.'), which no refusal should name
    if getattr(args, "out", None) == "":
        raise ConfigError("--out", "", "is empty: give a folder, or leave the flag out")
    if getattr(args, "spec", None) == "":
        raise ConfigError("spec", "", "is empty: give the spec's TOML file")
    if "" in (getattr(args, "data", None) or ()):
        raise ConfigError("DATA", "", "is empty: give a drop test's metadata TOML or CSV")


def _quiet_closed_stdout() -> None:
    """Point stdout's descriptor at nothing, so that the interpreter's last flush of what is
    still buffered does not fail on the closed pipe too (in-process callers whose stdout has
    no descriptor keep theirs)."""
    import os

    try:
        fd = sys.stdout.fileno()
    except (AttributeError, OSError, ValueError):
        return
    os.dup2(os.open(os.devnull, os.O_WRONLY), fd)


def main(argv=None) -> int:
    """Run one ``jaxland`` command (``argv``: its arguments; None: ``sys.argv[1:]``) and
    return its exit code. Ctrl-C and SIGTERM stop it with one line and the output folder as it
    was; the signal handlers found are restored on return."""
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(_join_negative_values(argv))
    from ._common import use_compilation_cache

    use_compilation_cache()
    import signal
    import threading

    from .._files import clear_interrupt, interrupt_handler, quiet_unraisable

    clear_interrupt()
    # only from the main thread, and only over Python's own handlers (not one a caller set):
    # Ctrl-C and a SIGTERM (a scheduler's stop) leave the output folder as it was, with one line
    main_thread = threading.current_thread() is threading.main_thread()
    own = {sig: before for sig, before in (
        (signal.SIGINT, signal.default_int_handler), (signal.SIGTERM, signal.SIG_DFL))
        if main_thread and signal.getsignal(sig) is before}
    for sig in own:
        signal.signal(sig, interrupt_handler)
    unraisable = sys.unraisablehook
    if own:  # the process's hook, from its main thread only
        sys.unraisablehook = quiet_unraisable(unraisable)
    try:
        return _run(args)
    finally:
        for sig, before in own.items():
            signal.signal(sig, before)
        if own:
            sys.unraisablehook = unraisable


def console() -> None:
    """The ``jaxland`` command's entry point: ``main``, then the process's exit with its
    code. An interrupt that arrives once the command has ended (during the interpreter's
    shutdown: JAX's exit handlers, a distributed run's last barrier) ends the process at once
    with that code: the output is written, or refused, and said."""
    import signal

    code = main(sys.argv[1:])
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, _exit_at_once(code))
    sys.exit(code)


def _exit_at_once(code: int):
    """A signal handler that ends the process with ``code`` (the command has ended: its output
    is written, or refused, and said)."""
    import os

    def handler(signum, frame):
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(code)
    return handler


def _run(args) -> int:
    """The command, its refusals and failures as exit codes, each said in one line."""
    import signal

    from .._files import interrupt_signal

    try:
        _refuse_empty_paths(args)
        code = args.func(args)
        sys.stdout.flush()  # a block-buffered report meets a closed pipe here, not at exit
        return code
    except ConfigError as err:
        print(f"jaxland: error: {err}", file=sys.stderr)
        return EXIT_INVALID
    except SimulationError as err:
        print(f"jaxland: numerical failure: {err}", file=sys.stderr)
        return EXIT_NUMERICAL
    except KeyboardInterrupt:
        print("jaxland: interrupted (nothing was written to the output folder)", file=sys.stderr)
        return EXIT_SIGNAL + interrupt_signal(signal.SIGINT)
    except BrokenPipeError:  # the reader of stdout stopped (| head): the report stops here
        _quiet_closed_stdout()
        try:  # stderr may be the same closed pipe (2>&1 | head)
            print("jaxland: standard output closed by its reader: the printed report stops "
                  "here (an output folder is written whole before its report, or not at all)",
                  file=sys.stderr)
        except BrokenPipeError:
            pass
        return EXIT_OS
    except OSError as err:  # a full disk: the output folder is left untouched
        print(f"jaxland: cannot write: {err}", file=sys.stderr)
        return EXIT_OS


if __name__ == "__main__":
    console()
