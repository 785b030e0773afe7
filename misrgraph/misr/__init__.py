"""MISR space: the SOM grid of each path with its blocks (:mod:`.som`), and MISR's orbit numbering
with orbit <-> path <-> time (:mod:`.orbits`). Depends on :mod:`misrgraph.model` only (numpy,
pyproj)."""
