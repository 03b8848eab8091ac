"""dvpmvs's tests, laid out as the package: ``tests/test_<module>.py`` for ``dvpmvs/<module>.py``,
``tests/patchmatch/`` for ``dvpmvs/patchmatch/``, ``tests/evaluation/`` for the harness and
``tests/plugins/`` for the built-in providers. What several test modules share is in
``tests/helpers.py`` (running the command, the documents' commands) and the scene builders
``tests/scenes.py``, ``plane_scenes.py``, ``prior_scenes.py``, ``onnx_models.py``."""
