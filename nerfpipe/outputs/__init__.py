"""What a trained model makes, as images and files: the one renderer of whole cameras in chunks
(:mod:`~nerfpipe.outputs.render`), camera-path renders for ``nerfpipe render`` and the render stage
(:mod:`~nerfpipe.outputs.novel_views`), depth colour maps, GIF/MP4 sequences and the run's figures. It
takes a :class:`~nerfpipe.models.base.Model` and the data containers; it never imports training, the
pipeline or the CLI, so the trainer's end-of-run outputs, the render stage, the viewer and mesh texturing
all use the same code.
"""
