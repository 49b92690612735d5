"""Stages chained over one run folder: :class:`~nerfpipe.pipeline.stages.Pipeline`, the stage API
(:class:`~nerfpipe.pipeline.stages.StageSpec`, :class:`~nerfpipe.pipeline.stages.StageContext`, markers,
:func:`~nerfpipe.pipeline.stages.atomic_path`) that the plugins in :mod:`nerfpipe.plugins` implement, many
captures as Ray tasks (:mod:`~nerfpipe.pipeline.many`) and ``report.html`` built from what each stage declares
it shows (:mod:`~nerfpipe.pipeline.report`, :mod:`~nerfpipe.pipeline.report_items`). Orchestration: it may
use every layer below; only the plugins, the commands and the CLI import it.
"""
