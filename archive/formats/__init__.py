"""Raw file formats, read and written without knowing sources or archives: ENVI cubes and headers
(:mod:`~archive.formats.envi`), ``.lcf`` navigation (:mod:`~archive.formats.lcf`), ``.times`` line
clocks (:mod:`~archive.formats.times`), ``.icp`` calibration packs (:mod:`~archive.formats.icp`) and
flight directory discovery (:mod:`~archive.formats.flight`)."""
