"""Built-in pipeline stages (registered through the ``nerfpipe.stages`` entry-point group)."""
