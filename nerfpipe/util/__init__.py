"""Plumbing every layer may use, and which imports nothing else of nerfpipe: the one user-facing error
(:mod:`~nerfpipe.util.errors`), atomic writes (:mod:`~nerfpipe.util.atomic`), path and output-folder
checks (:mod:`~nerfpipe.util.paths`), config dataclasses to dicts and back (:mod:`~nerfpipe.util.configs`),
entry-point plugin discovery (:mod:`~nerfpipe.util.registry`), the ``--device`` check
(:mod:`~nerfpipe.util.devices`), process settings and torch's global state (:mod:`~nerfpipe.util.runtime`,
:mod:`~nerfpipe.util.scoped`), the one-process-per-run-folder lock (:mod:`~nerfpipe.util.runlock`), the
progress bar and the axis vocabulary of tensor shapes (:mod:`~nerfpipe.util.typing`). The lowest layer.
"""
