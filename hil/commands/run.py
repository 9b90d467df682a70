"""`hil run SCENARIO`: fly one scenario file and write its report; exit 0 all checks passed, 1 a check
failed, 2 bad input (a gap too small for the vehicle among it, refused before take-off)."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from emulator.physics import backend_names
from hil.commands import output_folder, port_number, say_if_compiling
from hil.link.protocols import PROTOCOLS
from hil.runner import RunOptions, RunResult, RunSetupError, run_scenario
from hil.runner.emulator_side import EmulatorSide
from hil.scenario import ScenarioError, load_scenarios
from hil.scenario.schema import Scenario

if TYPE_CHECKING:
    from hil.view import ViewServer

EXIT_PASSED, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("run", help="fly one scenario file (every document in it) and write the reports")
    add_run_options(p)
    p.add_argument("scenario", metavar="SCENARIO", help="a *.scenario.yaml file")
    p.add_argument("--out", default=None, metavar="DIR", help="output folder (default reports/<scenario id>)")
    p.add_argument("--view", action="store_true",
                   help="serve a live view on 127.0.0.1 (URL printed): each scenario live in turn, "
                        "then the last one's replay until Ctrl-C")
    p.add_argument("--view-port", type=port_number, default=0, metavar="PORT",
                   help="the view's port (default: a free one)")
    p.add_argument("--mcap", action="store_true", help="also write run.mcap beside run.tlog (Foxglove)")
    p.set_defaults(func=main)


def add_run_options(p: argparse.ArgumentParser) -> None:
    """Options shared by `hil run` and `hil suite`."""
    p.add_argument("--pilot", default=None, help="fly with this pilot instead of the scenario's")
    p.add_argument("--realtime", action="store_true", default=None, help="real time instead of lockstep")
    p.add_argument("--seed", type=int, default=None, help="seed instead of the scenario's")
    p.add_argument("--backend", default=None, choices=backend_names(), help="physics backend")
    p.add_argument(
        "--vehicle",
        default=None,
        metavar="NAME|PATH",
        help="fly this vehicle profile instead of the scenario's (an opening narrower than its body grows)",
    )
    p.add_argument(
        "--protocol",
        default=None,
        choices=PROTOCOLS.keys(),
        help="the command link's protocol instead of the scenario's (docs/dji-open-link.md)",
    )
    p.add_argument(
        "--in-process",
        action="store_true",
        default=None,
        help="both sides in this process over memory links (default: two processes over ptys)",
    )
    p.add_argument(
        "--cold-start",
        action="store_true",
        default=False,
        help="start the onboard program as a new interpreter each run (default: forked warm from a "
        "pre-imported server)",
    )


def options_from(args: argparse.Namespace) -> RunOptions:
    return RunOptions(
        pilot=args.pilot,
        in_process=args.in_process,
        realtime=args.realtime,
        seed=args.seed,
        backend=args.backend,
        vehicle=args.vehicle,
        protocol=args.protocol,
        cold_start=args.cold_start,
    )


def run_one(scenario: Scenario, out_dir: Path, options: RunOptions, quiet: bool = False,
            view: ViewServer | None = None) -> RunResult:
    """Run one scenario, printing a progress line (to a terminal) and the verdict; ``view`` shows it live."""
    tty = sys.stderr.isatty() and not quiet
    watch = None
    if view is not None:
        from hil.view.live import run_source  # (the view server's imports only with --view)

        def watch(emu: EmulatorSide, events: Path) -> Callable[[], None]:
            view.live(run_source(emu, events, f"{scenario.id} (live)"))
            return view.hold  # before the emulator closes

    def progress(t: float, duration: float) -> None:
        if tty:
            print(f"\r  {scenario.id}: sim {t:5.2f} / {duration:g} s", end="", file=sys.stderr, flush=True)

    try:
        result = run_scenario(scenario, out_dir, options, progress=progress, watch=watch)
    finally:
        if view is not None:
            view.finish(out_dir)
    if tty:
        print("\r" + " " * 60 + "\r", end="", file=sys.stderr)
    s = result.summary
    rtf = s.get("real_time_factor")
    word = "PASSED" if result.passed else "REFUSED" if s.get("refused") else "FAILED"
    if s.get("refused"):  # never flown: the opening is too small for the body
        print(f"{word} {scenario.id}: refused before take-off: {s['refused']}")
        print(f"  report: {result.report_path}")
        return result
    print(
        f"{word} {scenario.id}: sim {s['sim_time_s']:.2f} s in {s['wall_time_s']:.2f} s wall"
        + (f" ({rtf:.1f}x real time)" if rtf else "")
    )
    for c in result.failed_checks:
        when = "" if c.time_s is None else f" at t={c.time_s:.3f} s"
        print(f"  failed {c.name}: expected {c.expected}, observed {c.observed}{when}")
    for ev in s["events"]:  # why the onboard program gave up the mission (the planner's detail too)
        if ev["source"] == "onboard" and ev["text"].startswith("abort: "):
            print(f"  onboard {ev['text']} at t={ev['time_s']:.3f} s")
    print(f"  report: {result.report_path}")
    return result


def read_scenario_file(path: Path, prog: str) -> list[Scenario] | None:
    """The scenarios of ``path``; None after printing why it cannot be read or is invalid (exit 2)."""
    try:
        return load_scenarios(path)
    except ScenarioError as exc:
        print(f"{prog}: {exc}", file=sys.stderr)
    except OSError as exc:
        print(f"{prog}: cannot read {path}: {exc.strerror or exc}", file=sys.stderr)
    return None


def main(args: argparse.Namespace) -> int:
    path = Path(args.scenario)
    scenarios = read_scenario_file(path, "hil run")
    if scenarios is None:
        return EXIT_BAD_INPUT
    if not scenarios:
        print(f"hil run: {path} holds no scenario", file=sys.stderr)
        return EXIT_BAD_INPUT
    options = options_from(args)
    base = output_folder(args.out or "reports", "hil run")
    if base is None:
        return EXIT_BAD_INPUT
    say_if_compiling("hil run")
    failed = False
    view = None
    if args.view:
        from hil.view import ViewServer  # (the view server's imports only with --view)

        try:
            view = ViewServer(port=args.view_port)
        except OSError as exc:
            print(f"hil run: --view: cannot serve on 127.0.0.1:{args.view_port}: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        print(f"view: {view.url}", flush=True)
    for s in scenarios:
        if s.skip:
            print(f"SKIPPED {s.id}: {s.skip}")
            continue
        out = base if (args.out and len(scenarios) == 1) else base / s.id
        try:
            result = run_one(s, out, options, view=view)
        except (RunSetupError, ValueError) as exc:
            print(f"hil run: {s.source}:{s.line}: {exc}", file=sys.stderr)
            return EXIT_BAD_INPUT
        if result.summary.get("refused") and not result.passed:
            return EXIT_BAD_INPUT  # a gap the vehicle cannot pass: the scenario asks the impossible
        failed = failed or not result.passed
        if args.mcap:
            from hil.report.mcap_log import write_mcap  # (the mcap writer only with --mcap)

            try:
                print(f"  mcap: {write_mcap(out)}")
            except ValueError as exc:
                print(f"hil run: --mcap: {exc}", file=sys.stderr)
                return EXIT_BAD_INPUT
    if view is not None:
        from hil.view.server import serve_until_stopped  # (the view server only with --view)

        print(f"view: the finished run at {view.url}; Ctrl-C to stop", flush=True)
        serve_until_stopped(view)
    return EXIT_FAILED if failed else EXIT_PASSED
