"""Seeing and touching the tissue: an animated demo and a live viewer in the browser.

=====================  ===========================================================================
:mod:`.animation`      frames of a run (textured, shaded surface beside the deformed volume render,
                       time and tool force written on them) into an animated GIF
:mod:`.session`        a simulation the viewer drives: play, pause, reset, drag, tool, cut, tissue terms
:mod:`.server`         the local viewer: page and WebSocket on loopback, token and Origin checked
:mod:`.commands`       ``torchdeform view SCENE.toml``
=====================  ===========================================================================

Nothing here is imported by the rest of the library; the viewer's server library (``websockets``)
is imported only by the code that serves.
"""
