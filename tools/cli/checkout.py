"""``pfma checkout``: scripted per-channel checkout of the rack with a report.

Without ``--buffer`` it starts its own simulated rack and I/O service in this process
in simulated time (deterministic, a few seconds); operator steps are done by the fake
rack's stimulus. With ``--buffer NAME`` it checks the rack behind a running service in
real time and prompts the operator ("deflect CAE up") for the hand controller and the
user I/F box (``--non-interactive`` skips those steps), and before the joints group asks
the state of the servo chassis' front-panel switches (``--panel-off`` states it instead,
and a non-interactive or simulated run without it assumes them all on: the report says
which). The logic lives in
``tools.checkout``; tolerances in ``tools/checkout/checkout_default.toml`` (``--config``
overrides them). Exit code 0 only when every check passed.
"""

from __future__ import annotations

import argparse
import sys

from tools.checkout.config import GROUPS
from tools.cli.args import add_sim_errors, nonneg_float


def add_parser(sub):
    p = sub.add_parser("checkout", help="scripted per-channel checkout with a JSON/HTML report",
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rack", default="fake",
                   help="fake (the IRSS rack, default) or a rack TOML; with --buffer: the rack the service runs")
    p.add_argument("--buffer", default=None, metavar="NAME",
                   help="check a running service's rack through its Bit3 buffer (real time)")
    p.add_argument("--non-interactive", action="store_true",
                   help="no operator prompts: on a real rack operator steps are skipped")
    p.add_argument("-k", "--keep-going", action="store_true", help="do not stop at the first failure")
    p.add_argument("--json", metavar="FILE", nargs="?", const="-",
                   help="write the JSON report to FILE; --json alone prints it on stdout as one "
                        "JSON document (progress and the summary then go to stderr)")
    p.add_argument("--html", metavar="FILE", help="write the standalone HTML report")
    p.add_argument("--only", nargs="+", choices=GROUPS, metavar="GROUP",
                   help=f"run only these groups ({', '.join(GROUPS)})")
    p.add_argument("--config", metavar="FILE", help="tolerances merged over tools/checkout/checkout_default.toml")
    p.add_argument("--wait", type=nonneg_float, default=30.0, metavar="S",
                   help="with --buffer: wait this long for the service (0 = forever; default 30)")
    p.add_argument("--sim-fault", action="append", default=[], metavar="SPEC",
                   help="simulated rack only: inject a fault first, any spec of `pfma fault list` "
                        "(e.g. tach-reversed:JOINT, adc-dead:SIGNAL=VOLTS, resolver-los:SIGNAL, "
                        "ft-noise, bus-error:BOARD); repeatable; docs/faults.md")
    add_sim_errors(p)
    p.add_argument("--panel-off", action="append", default=[], metavar="SWITCHES",
                   help="state the servo chassis' front panel instead of being asked: the switches "
                        "that are off, comma-separated: 28v, 15v, pwm:JOINT (or pwm:gripper), "
                        "brake:JOINT, pwm:all, brake:all; 'none' = every switch on. Without it a "
                        "non-interactive or simulated run assumes every switch on (the report says so)")
    p.add_argument("-q", "--quiet", action="store_true", help="print only failures and the summary")
    return p


def _usage_error(args, rack_path: str | None):
    """``(message, panel)``: the first usage mistake of ``--panel-off``/``--sim-fault`` (exit 2
    before anything is built; None if none), and the panel stated by ``--panel-off``."""
    from pfma.errors import ConfigError
    from pfma.rack import load_rack
    from tools.checkout.panel import COMMAND_LINE, PanelState, parse_panel_off
    panel = None
    if args.panel_off:
        try:
            panel = PanelState(parse_panel_off(args.panel_off, load_rack(rack_path).joints), COMMAND_LINE)
        except ConfigError as err:
            return f"pfma checkout: {err}", None
    if args.sim_fault and args.buffer:
        return "pfma checkout: --sim-fault needs the simulated rack (no --buffer)", panel
    if args.sim_errors and args.buffer:
        return "pfma checkout: --sim-errors gives the simulated rack its imperfections (no --buffer)", panel
    if args.sim_fault:
        from sim.faults import parse_fault
        rack = load_rack(rack_path)
        for spec in args.sim_fault:
            try:
                parse_fault(spec, rack)
            except ConfigError as err:
                return f"pfma checkout: --sim-fault {err}", panel
    return None, panel


def _target(args, rack_path: str | None, cfg):
    """``(target, interactive)``: the running service's rack (``--buffer``) or a simulated one
    (the stimulus acts for the operator)."""
    from tools.checkout import LiveTarget, make_sim_target
    if args.buffer:
        from pfma.rack import load_rack
        from tools.attach import attach_waiting
        client = attach_waiting(args.buffer, rack_path, wait_s=args.wait)
        target = LiveTarget(client, load_rack(rack_path),
                            service_timeout_s=cfg.num("checkout", "service_timeout_s"))
        return target, not args.non_interactive
    return make_sim_target(rack_path, sim_errors=args.sim_errors), False


def _check(args, target, cfg, panel, interactive: bool, text, bars):
    """Inject the simulated faults, run the checkout; the Checkout and its report."""
    from tools.checkout import Checkout
    for spec in args.sim_fault:
        print(f"pfma checkout: injected fault: {target.inject_fault(spec)}", file=text)

    def say(line: str) -> None:
        if not args.quiet or line.startswith(("FAIL", ">>>")):
            if bars is not None:
                bars.say(line)
            else:
                print(line, file=text, flush=True)

    def ask(prompt: str) -> str:
        """The operator's answer (the panel questions): the bar leaves the screen and the
        prompt goes where the row lines go (stdout may be the JSON document)."""
        if bars is not None:
            bars.pause()
        print(prompt, end="", file=text, flush=True)
        return input()
    chk = Checkout(target, cfg, keep_going=args.keep_going, only=args.only,
                   interactive=interactive, say=say, progress=bars.update if bars is not None else None,
                   panel=panel, ask=ask)
    return chk, chk.run()


def _say_report(args, report, text, bars) -> None:
    """The summary, the JSON and HTML reports."""
    from tools.cli.output import console, print_json
    print(file=text)
    if bars is not None:
        console(text).print(report.summary_table())
    else:
        for line in report.summary_lines():
            print(line, file=text)
    if args.json == "-":
        print_json(report.as_dict())
    elif args.json:
        print(f"JSON report: {report.write_json(args.json)}", file=text)
    if args.html:
        print(f"HTML report: {report.write_html(args.html)}", file=text)


def run(args) -> int:
    from tools.checkout import load_checkout_config
    from tools.cli.output import ProgressBars, is_terminal

    cfg = load_checkout_config(args.config)
    rack_path = None if args.rack in ("fake", "default") else args.rack
    mistake, panel = _usage_error(args, rack_path)
    if mistake is not None:
        print(mistake, file=sys.stderr)
        return 2
    target, interactive = _target(args, rack_path, cfg)
    text = sys.stderr if args.json == "-" else sys.stdout  # stdout is the JSON document then
    bars = ProgressBars(text) if is_terminal(text) else None
    try:
        chk, report = _check(args, target, cfg, panel, interactive, text, bars)
    finally:
        if bars is not None:
            bars.close()
        target.close()
    _say_report(args, report, text, bars)
    if chk.interrupted:
        return 130
    return 0 if report.passed else 1
