"""`wtbench report`: a static results site of a folder of runs (docs/report.md).

:mod:`.gather` reads the run folders (state, evaluation record, per-frame scores, scene), :mod:`.images`
makes the viewer's thumbnails and error heat maps, :mod:`.site` renders the Jinja2 templates of
``templates/`` into a folder that opens from the file system.
"""
