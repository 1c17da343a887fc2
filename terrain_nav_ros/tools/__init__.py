"""The ``terrain-nav`` command and what it runs: the graph runner, bags, replay and its
report, the flight simulator and the studies behind ``evaluate``.

Tools start nodes as processes (by executable name), never by importing them.
"""
