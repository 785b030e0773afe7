"""MkDocs build hook: the command-line reference is generated from the CLI itself."""

from __future__ import annotations

MARKERS = {
    "<!-- cli-reference -->": ("misrgraph.commands.reference", "cli_markdown"),
    "<!-- noise-levels -->": ("misrgraph.model.noise", "levels_markdown"),
}


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ANN001 - MkDocs' hook signature
    import importlib

    for marker, (module, function) in MARKERS.items():
        if marker in markdown:
            markdown = markdown.replace(marker, getattr(importlib.import_module(module), function)())
    return markdown
