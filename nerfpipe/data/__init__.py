"""Scenes as data: the containers and geometry between the input files and the models. The one camera
model (:mod:`~nerfpipe.data.cameras`), rays and samples along them (:mod:`~nerfpipe.data.rays`,
:mod:`~nerfpipe.data.samples`) as batch-shaped tensor dataclasses, the scene record every adapter returns
(:mod:`~nerfpipe.data.scene`) with its images (:mod:`~nerfpipe.data.image_file`), world normalisation,
background colours, camera paths (generated orbits and nerfstudio's ``camera_path.json``), the
independent convention checks, and the synthetic scenes with known geometry. Built on
:mod:`nerfpipe.functional` and :mod:`nerfpipe.util` only; models, training and the pipeline build on it.
"""
