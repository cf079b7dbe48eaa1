"""``archive watch``: follow recorder folders while a flight records, show each cube georectified as
the recorder closes it, and ingest each flight once it has stopped (docs/watch.md, DESIGN 12).

- :mod:`archive.watch.cubes`: when a cube is complete (its header written last; the ``.bil``,
  ``.bil.times`` and ``.lcf`` agree with it and have stopped growing), its image set (the flight);
- :mod:`archive.watch.follow`: the folders' cubes over time (complete, growing, stalled, changed,
  gone), one state machine driven by scans;
- :mod:`archive.watch.stage`: folders of links holding exactly one cube or one flight's files;
- :mod:`archive.watch.live`: what ``GET /api/live`` answers and the cubes the viewer serves;
- :mod:`archive.watch.command`: the command (inotify or polling, the viewer, the idle ingest, signals);
- :mod:`archive.watch.arguments`: its parser.
"""
