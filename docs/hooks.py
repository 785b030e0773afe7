"""MkDocs build hook: the command-line reference is generated from the CLI itself."""

from __future__ import annotations

MARKER = "<!-- cli-reference -->"


def on_page_markdown(markdown: str, page, config, files) -> str:  # noqa: ANN001 - MkDocs' hook signature
    if MARKER not in markdown:
        return markdown
    from misrgraph.commands.reference import cli_markdown

    return markdown.replace(MARKER, cli_markdown())
