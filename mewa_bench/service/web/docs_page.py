"""/docs: the API's reference as one self-contained page, built from the OpenAPI description (no CDN, no script)."""

from __future__ import annotations

from typing import Any

from mewa_bench.service.web.layout import esc, page

_METHODS = ("get", "post", "put", "patch", "delete")


def _parameters(operation: dict[str, Any]) -> str:
    """The operation's path and query parameters as a list."""
    items = []
    for p in operation.get("parameters", []):
        schema = p.get("schema", {})
        bounds = "".join(f", {k} {schema[k]}" for k in ("minimum", "maximum") if k in schema)
        items.append(f"<li><code>{esc(p.get('name'))}</code> ({esc(p.get('in'))}, {esc(schema.get('type', 'any'))}"
                     f"{esc(bounds)}{', required' if p.get('required') else ''})</li>")
    body = operation.get("requestBody", {}).get("content", {})
    for media in body:
        items.append(f"<li>body: <code>{esc(media)}</code></li>")
    return f"<ul>{''.join(items)}</ul>" if items else ""


def docs_html(openapi: dict[str, Any]) -> str:
    """Every path and method with its summary, description and parameters; the JSON at /openapi.json."""
    sections = []
    for path, methods in openapi.get("paths", {}).items():
        for method in _METHODS:
            if method not in methods:
                continue
            operation = methods[method]
            sections.append(f'<section class="operation" data-path="{esc(path)}" data-method="{method}">'
                            f"<h3><code>{method.upper()} {esc(path)}</code></h3>"
                            f"<p>{esc(operation.get('summary', ''))}</p>"
                            f"<p class=\"muted\">{esc(operation.get('description', ''))}</p>"
                            f"{_parameters(operation)}</section>")
    info = openapi.get("info", {})
    intro = (f"<p>{esc(info.get('description', ''))}</p><p>Version {esc(info.get('version', ''))}. The machine-readable "
             f'description is <a href="/openapi.json">/openapi.json</a>. Errors are JSON '
             f"<code>{{\"error\": code, \"detail\": message}}</code>.</p>")
    return page("API reference", intro + "\n".join(sections))
