"""``dermis report [SCENE]``: build what the PDF report needs (renders, differences) and say
where it is.  A command of the report's package, not of the engine: the engine runs nodes up
to the ``report`` stage like any other (``dermis run --until report``); this command adds the
check that the scene makes a report at all, with the rule it breaks when it does not."""
from __future__ import annotations

import os

from dermis.pipeline import api
from dermis.pipeline.cli import progress_bars
from dermis.pipeline.config import load_scene
from dermis.pipeline.errors import ConfigError
from dermis.pipeline.plan import build_graph
from dermis.pipeline.registry import stage

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    rp = sub.add_parser("report", help="build the renders, difference images and PDF report")
    rp.add_argument("scene", nargs="?", default=None,
                    help="scene TOML (default: the embedded scene, scenes/default.toml)")
    rp.add_argument("--cache", default=None, help="cache directory (or $DERMIS_CACHE)")
    rp.add_argument("-j", "--jobs", default=None, metavar="N",
                    help="nodes run at once on threads (or $DERMIS_JOBS; default 2); the "
                         "results are the same for any N")
    rp.add_argument("--device", default=None, help="OpenCL device: P:D, P, or a name substring")
    rp.add_argument("-q", "--quiet", action="store_true", help="no progress bars")
    rp.set_defaults(func=run)


def run(args) -> int:
    scene = load_scene(args.scene)
    report = stage("report").NAME
    nodes, _ = build_graph(scene)
    if not any(n.stage == report for n in nodes.values()):
        baseline = stage("differences").BASELINE
        models = "[" + ", ".join(f'"{m}"' for m in scene.render.models) + "]"
        raise ConfigError(f"{scene.path}: render.models = {models}: this scene makes no "
                          f'report; the report compares the models with "{baseline}", so '
                          f'render.models must list "{baseline}" and at least one other '
                          "model (dermis run builds the images alone)")
    summary = api.run(scene, cache=args.cache, until=report, device=args.device,
                      progress=None if args.quiet else progress_bars(), jobs=args.jobs)
    print(summary.table())
    out = os.path.join(scene.output.output_dir, scene.scene.name, "report", "report.pdf")
    print(f"report: {out}")
    return 0
