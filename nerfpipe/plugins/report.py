"""Stage ``report``: ``report.html``, one self-contained page of everything the run produced.

Built by :func:`nerfpipe.pipeline.report.write_report` from whatever is in the run folder (missing
artifacts are listed as "not produced"), so it can run after any chain, or alone with
``nerfpipe stage report RUN_DIR``. It requires nothing and is the last stage of the default chain.
"""

from nerfpipe.pipeline.report import REPORT_FILE, ReportConfig
from nerfpipe.pipeline.stages import StageContext, StageSpec


def run(config: ReportConfig, ctx: StageContext) -> "dict[str, object]":
    from nerfpipe.pipeline.report import write_report

    path = write_report(ctx.run_dir, config)
    ctx.log.info("report: %s (%.0f kB)", path, path.stat().st_size / 1024)
    return {REPORT_FILE: path}


STAGE = StageSpec(
    name="report",
    description="report.html: scene, check, metrics, curves, orbit/depth GIFs, mesh, timings in one file",
    config=ReportConfig,
    run=run,
    light=True,
    produces=(REPORT_FILE,),
)
