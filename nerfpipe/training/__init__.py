"""Training a model on a scene into a run folder, and reading it back: the loop
(:mod:`~nerfpipe.training.trainer`), training rays (:mod:`~nerfpipe.training.pixel_sampler`), validation
and end-of-run outputs (:mod:`~nerfpipe.training.evaluation`), safetensors checkpoints, data-parallel
collectives (:mod:`~nerfpipe.training.distributed`), the run folder with :func:`~nerfpipe.training.runs.load_run`,
and the measuring tools (operation counts, the speed-against-error benchmark). Above the models and
:mod:`nerfpipe.outputs`; below the pipeline, the viewer and the CLI.
"""
