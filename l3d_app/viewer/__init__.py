"""The live viewer: a page in the browser (viser) that renders the current model from the
browser's camera while a task trains, or a finished run (``task=view``).

The viewer takes plain callables (take a snapshot of the model, render a snapshot through
:class:`~l3d_app.geometry.cameras.Cameras`), so it knows no model; tasks wire it
(``pipelines/live_viewer.py``)."""
