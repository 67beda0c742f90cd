"""``mi-gs sweep SPEC.toml -o OUT``: many training runs (datasets x settings x seeds) as Ray tasks, on this machine
or a cluster (``--address``); see :mod:`mi_gaussians.cluster.sweep`."""

from __future__ import annotations

from pathlib import Path

from ..cluster.ray_cluster import Waits
from .args import add_output, existing, positive_float
from .errors import EXIT_RUNS_FAILED, note


def add_parser(sub) -> None:
    s = sub.add_parser("sweep", help="train every run of a spec (datasets x settings x seeds) as Ray tasks, on this "
                                     "machine or a Ray cluster; results.csv / results.md")
    s.add_argument("spec", help="the sweep's TOML file (datasets, iterations, seeds, [set], [grid], [resources])")
    add_output(s, "output folder: runs/<dataset>-<setting>-s<seed>/, references/, results.csv, results.md",
               overwrite="start every run again (the cached references are kept)")
    s.add_argument("--address", default=None,
                   help="join this Ray cluster (e.g. HEAD:6379, or auto); its nodes must see the output folder at the "
                        "same path (default: start a local one on this machine)")
    w = Waits()
    s.add_argument("--connect-timeout", type=positive_float, default=w.connect, metavar="SECONDS",
                   help=f"the longest wait for the cluster at --address to answer (default {w.connect:g})")
    s.add_argument("--check-timeout", type=positive_float, default=w.shared_folder, metavar="SECONDS",
                   help=f"the longest wait for every node to answer the shared-folder check (default "
                        f"{w.shared_folder:g})")
    s.add_argument("--stop-timeout", type=positive_float, default=w.stop, metavar="SECONDS",
                   help=f"after SIGTERM / SIGHUP / Ctrl-C, the longest wait for the running runs to checkpoint; those "
                        f"still going are then ended and resume from their previous checkpoint (default {w.stop:g})")
    s.add_argument("--quiet", action="store_true", help="no progress bar and no information lines (warnings stay)")


def run(args) -> int:
    import mitsuba as mi

    from ..cluster.sweep import SweepStopped, run_sweep
    from ..runs import quiet, to_stderr
    from ..cluster.sweep_spec import read_spec
    from ..io_utils import check_output_folder

    spec = read_spec(existing(args.spec), cuda=mi.variant().startswith("cuda"))
    for line in spec.notes:
        note(line)
    out = Path(args.output)
    check_output_folder(out)
    try:
        rows = run_sweep(spec, out, mi.variant(), address=args.address, overwrite=args.overwrite,
                         progress=not args.quiet, log=quiet(to_stderr) if args.quiet else to_stderr,
                         waits=Waits(args.connect_timeout, args.check_timeout, args.stop_timeout))
    except SweepStopped as e:
        import signal
        import sys

        name = signal.Signals(e.signum).name
        saved = sum(r["error"].startswith("stopped at iteration") for r in e.stopped)
        others = len(e.stopped) - saved
        more = f", {others} before training began or ended after --stop-timeout" if others else ""
        print(f"mi-gs: sweep stopped by {name}: {saved} run{'s' if saved != 1 else ''} stopped at a checkpoint{more} "
              f"({out / 'results.csv'}); the same command resumes", file=sys.stderr, flush=True)
        return 128 + e.signum
    failed = [r for r in rows if r["status"] != "done"]
    print((out / "results.md").read_text(), flush=True)
    print(f"{len(rows) - len(failed)} of {len(rows)} runs done -> {out / 'results.csv'}", flush=True)
    return EXIT_RUNS_FAILED if failed else 0
