"""Print ``name==floor`` for every ``name>=floor`` runtime requirement in pyproject.toml (core and
the runtime extras sim, viz, fast; the test tools and pyceres are not pinned): the constraints
file of .ci/min-versions."""

from __future__ import annotations

import re
import sys
from pathlib import Path

TEXT = (Path(__file__).resolve().parents[1] / "pyproject.toml").read_text()
RUNTIME_EXTRAS = ("sim", "viz", "fast")

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10: the two lists are plain enough for a pattern
    tomllib = None

if tomllib is not None:
    project = tomllib.loads(TEXT)["project"]
    reqs = list(project["dependencies"]) + [r for e in RUNTIME_EXTRAS for r in project["optional-dependencies"][e]]
else:
    core = re.search(r"^dependencies\s*=\s*\[(.*?)\]", TEXT, re.S | re.M)
    reqs = re.findall(r'"([^"]+)"', core.group(1) if core else "")
    for e in RUNTIME_EXTRAS:
        m = re.search(rf"^{e}\s*=\s*\[(.*?)\]", TEXT, re.M)
        reqs += re.findall(r'"([^"]+)"', m.group(1) if m else "")
seen = set()
for r in reqs:
    m = re.fullmatch(r"\s*([A-Za-z0-9_.\-]+)\s*>=\s*([0-9][^,;\s]*)\s*", r)
    if m and m.group(1).lower() not in seen:
        seen.add(m.group(1).lower())
        sys.stdout.write(f"{m.group(1)}=={m.group(2)}\n")
