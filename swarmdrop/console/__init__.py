"""`swarmdrop console`: the operator's web page for a swarm of any size (docs/console.md).

Modules (none imports aiohttp but server.py, and nothing here is on the agent's path):

    cli.py       the command line; imports the rest only when it runs
    protocol.py  the websocket protocol: the packed binary frame, message kinds
    mission.py   the mission as drawn: origin, obstacles, geofence, path, slots
    live.py      the live feed: the swarm link (states, plans) and a GCS link, checked
    replay.py    a recorded run (telemetry.npz, .tlog) and its playhead
    commands.py  operator commands: checked, made by companion.commands, signed, sent
    feeds.py     live and replay behind one interface; fleet health
    server.py    the aiohttp server: page, assets, websocket
    static/      the page: index.html, console.css, console.js, geo.js (no CDN, no build step)
"""
