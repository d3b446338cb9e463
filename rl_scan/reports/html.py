"""The report's Markdown as one self-contained HTML page (markdown-it-py, figures inlined)."""

from __future__ import annotations

import base64
from pathlib import Path

STYLE = ("body{font-family:sans-serif;max-width:1000px;margin:2em auto;padding:0 1em}"
         "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;"
         "padding:4px 8px;font-size:13px}th{background:#f3f3f3}img{max-width:100%}")


def to_html(markdown: str, out: Path) -> str:
    """HTML of ``markdown`` (CommonMark + tables); images relative to ``out`` are inlined
    as data URIs so the page can be mailed or archived on its own."""
    from markdown_it import MarkdownIt

    md = MarkdownIt("commonmark").enable("table")
    default_image = md.renderer.rules["image"]

    def inline_image(renderer, tokens, idx, options, env):
        token = tokens[idx]
        path = Path(out) / token.attrGet("src")
        if path.is_file():
            data = base64.b64encode(path.read_bytes()).decode()
            token.attrSet("src", f"data:image/png;base64,{data}")
        return default_image(tokens, idx, options, env)

    md.add_render_rule("image", inline_image)
    return ("<!doctype html><html><head><meta charset='utf-8'><title>rl-scan report</title>"
            f"<style>{STYLE}</style></head><body>{md.render(markdown)}</body></html>")
