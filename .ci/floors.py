"""Print ``name==floor`` for every ``name>=floor`` runtime requirement in pyproject.toml (core and
the runtime extras sim, viz, fast; the test tools and pyceres are not pinned): the constraints
file of .ci/min-versions."""

from __future__ import annotations

import re
import sys
import tomllib
from pathlib import Path

project = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text())["project"]
reqs = list(project["dependencies"])
for name in ("sim", "viz", "fast"):
    reqs += project["optional-dependencies"][name]
seen = set()
for r in reqs:
    m = re.fullmatch(r"\s*([A-Za-z0-9_.\-]+)\s*>=\s*([0-9][^,;\s]*)\s*", r)
    if m and m.group(1).lower() not in seen and m.group(1).lower() != "misrgraph":
        seen.add(m.group(1).lower())
        sys.stdout.write(f"{m.group(1)}=={m.group(2)}\n")
