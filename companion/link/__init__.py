"""The companion's MAVLink link layer: framing (``framing``), a lean codec (``wire``)
and the project dialect (``msgdef``).

Why a package of its own: the onboard computer talks MAVLink at a few hundred
messages per second and must not pay for pymavlink's parser or import numpy to do
so; everything here is stdlib plus mavgen-generated message classes.
"""
