"""Everything the add-on keeps in memory for the open .blend, in one object with one `clear()`: what each preview
shows, the status lines, the pending preview work and, once torch is loaded, the model / edit-state / atlas
caches. Loading another .blend or unregistering calls `STATE.clear()`."""
from __future__ import annotations

import sys


class AddonState:
    def __init__(self):
        self.records: dict = {}   # object name -> preview.PreviewRecord (the full-resolution preview it shows)
        self.written: dict = {}   # object name -> raw pixels last written into its preview (any level)
        self.status: dict = {}    # object name -> one line for the panels
        # how often work was actually done (tests check the caching and the scheduling)
        self.counts = {"rendered": 0, "levels": 0, "transfers": 0, "cancelled": 0, "requests": 0, "jobs": 0}
        self.dirty = False        # something changed since the last preview job started
        self.generation = 0       # bumped by every change; a job started under an older one is cancelled
        self.scene = ""           # the scene the last change came from
        self.job = None           # the running preview job (a generator of small steps)
        self.job_generation = -1
        self.rendering = False    # a render job runs: previews wait
        self.busy = False         # a synchronous preview update runs (guards against re-entry)
        self.handler_ms: list = []  # duration of the last handler calls (ms), newest last, at most 1000
        self.progress: list = []  # fractions shown by the last synchronous preview update (wm progress)
        self.outlines: dict = {}  # model file -> (its size and mtime, chart outlines in UV space [S, 2, 2])

    def forget_previews(self) -> None:
        """Forget what was written into the preview images (after an undo: the images may hold other pixels, which
        must never be mistaken for paint)."""
        self.records.clear()
        self.written.clear()

    def cancel(self) -> None:
        if self.job is not None:
            self.job.close()
            self.job = None
            self.counts["cancelled"] += 1

    def clear(self) -> None:
        """Forget everything: previews, status, pending work and the torch-side caches."""
        self.cancel()
        self.forget_previews()
        self.status.clear()
        self.dirty = False
        self.handler_ms.clear()
        self.outlines.clear()
        if "torch" in sys.modules:
            from ..bridge import deps

            if deps.torch_status().available:
                from ..bridge import frame_renderer
                from . import scene_inputs

                frame_renderer.STATES.clear()
                frame_renderer.MODELS.clear()
                scene_inputs.ATLASES.clear()


STATE = AddonState()
