"""The operator's console in a browser (`collector web`): fleet health, live RSSI and runs.

``snapshot`` turns the collector's status replies into what the page shows (pure, tested on its
own); ``server`` is the Starlette app that polls the collector once a second and pushes each
snapshot to every open page over server-sent events, and takes start/stop from the page.
"""
