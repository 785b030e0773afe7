"""MkDocs build hook: the CLI reference, the noise levels and the sensitivity table come from the code."""

from __future__ import annotations

MARKERS = {
    "<!-- cli-reference -->": ("misrgraph.commands.reference", "cli_markdown"),
    "<!-- noise-levels -->": ("misrgraph.model.noise", "levels_markdown"),
    "<!-- table3 -->": ("misrgraph.evaluate.sensitivity", "table3_markdown"),
}


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ANN001 - MkDocs' hook signature
    import importlib

    for marker, (module, function) in MARKERS.items():
        if marker in markdown:
            markdown = markdown.replace(marker, getattr(importlib.import_module(module), function)())
    return markdown
