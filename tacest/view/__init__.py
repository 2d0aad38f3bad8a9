"""Show what was recorded and learned: animations a person opens without tacest.

- :mod:`tacest.view.scene`: what to draw, from a run file, an estimate file or both;
- :mod:`tacest.view.anim2d`: 2-D GIF / MP4 (matplotlib);
- :mod:`tacest.view.html3d`: 3-D interactive HTML (one self-contained file).

``tacest view`` (cli/view.py) is the command.
"""
