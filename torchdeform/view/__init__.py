"""Seeing and touching the tissue: a live viewer in the browser (the run's animation is :mod:`torchdeform.scene.animation`).

=====================  ===========================================================================
:mod:`.session`        a simulation the viewer drives: play, pause, reset, drag, tool, cut, tissue terms
:mod:`.server`         the local viewer: page and WebSocket on loopback, token and Origin checked
:mod:`.commands`       ``torchdeform view SCENE.toml``
=====================  ===========================================================================

Nothing here is imported by the rest of the library; the viewer's server library (``websockets``)
is imported only by the code that serves.
"""
