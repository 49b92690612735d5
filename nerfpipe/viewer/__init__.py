"""``nerfpipe view``: a browser viewer (viser) of a dataset or a trained run, and of training as it runs.

Modules: :mod:`~nerfpipe.viewer.content` (what is drawn, as arrays), :mod:`~nerfpipe.viewer.progressive`
(the live render, coarse to fine), :mod:`~nerfpipe.viewer.server` (the viser server and its panel),
:mod:`~nerfpipe.viewer.source` (a run or dataset folder opened for viewing),
:mod:`~nerfpipe.viewer.training` (the viewer attached to a training loop) and
:mod:`~nerfpipe.viewer.headless` (headless Chromium driving the page, for tests and benchmarks).
Camera path files are :mod:`nerfpipe.data.camera_path`. viser is imported only when a viewer starts.
"""
