"""mkdocs hook: field tables generated from the package's JSON Schemas.

A page line `<!-- schema: NAME -->` becomes the title, description and a table of every
field of `moirejax/data_schema/NAME.schema.json` (nested objects as dotted names, array
items as `name[]`), so the data-format page cannot drift from the schemas the code
validates against.
"""

import importlib.resources
import json
import re
from typing import Any


_MARKER = re.compile(r"^<!-- schema: ([a-z_]+) -->$", re.MULTILINE)


def _load(name: str) -> dict[str, Any]:
    schema = importlib.resources.files("moirejax").joinpath("data_schema", f"{name}.schema.json")
    return json.loads(schema.read_text(encoding="utf-8"))


def _resolve(node: dict[str, Any], root: dict[str, Any]) -> dict[str, Any]:
    """Follow a local `$ref`, keeping the referring node's own keys (its description)."""
    if "$ref" not in node:
        return node
    target: Any = root
    for part in node["$ref"].removeprefix("#/").split("/"):
        target = target[part]
    return {**_resolve(target, root), **{k: v for k, v in node.items() if k != "$ref"}}


def _text(text: str) -> str:
    """Schema text is plain text: keep its brackets (not links) and pipes (not cells) literal."""
    for char in "[]|":
        text = text.replace(char, "\\" + char)
    return text.replace("\n", " ")


def _code(value: Any) -> str:
    return f"`{json.dumps(value)}`"


def _bounds(node: dict[str, Any]) -> list[str]:
    words = []
    for key, symbol in (("minimum", "≥"), ("exclusiveMinimum", ">"), ("maximum", "≤"), ("exclusiveMaximum", "<")):
        if key in node:
            words.append(f"{symbol} {node[key]}")
    if "minItems" in node or "maxItems" in node:
        low, high = node.get("minItems"), node.get("maxItems")
        words.append(f"{low} items" if low == high else f"{low or 0}..{high if high is not None else ''} items")
    if node.get("uniqueItems"):
        words.append("unique")
    if "minLength" in node:
        words.append(f"length ≥ {node['minLength']}")
    if "pattern" in node:
        words.append(f"matches `{node['pattern']}`")
    return words


def _type(node: dict[str, Any], root: dict[str, Any]) -> str:
    node = _resolve(node, root)
    if "const" in node:
        return f"always {_code(node['const'])}"
    if "enum" in node:
        return "one of " + ", ".join(_code(v) for v in node["enum"])
    for key, joiner in (("oneOf", " or "), ("anyOf", " or ")):
        if key in node:
            return joiner.join(_type(option, root) for option in node[key])
    kinds = node.get("type", "any")
    kinds = " or ".join(kinds) if isinstance(kinds, list) else kinds
    if kinds == "array" and isinstance(node.get("items"), dict):
        kinds = f"array of {_type(node['items'], root)}"
    if kinds == "object" and isinstance(node.get("additionalProperties"), dict) and "properties" not in node:
        kinds = f"object of {_type(node['additionalProperties'], root)}"
    extra = _bounds(node)
    return kinds + (f" ({', '.join(extra)})" if extra else "")


def _rows(node: dict[str, Any], root: dict[str, Any], prefix: str) -> list[tuple[str, str, bool, str]]:
    """(field, type, required, description) of every property, depth first."""
    node = _resolve(node, root)
    properties: dict[str, Any] = {}
    required: set[str] = set(node.get("required", []))
    for part in node.get("allOf", []):
        part = _resolve(part, root)
        properties.update(part.get("properties", {}))
        required |= set(part.get("required", []))
    properties.update(node.get("properties", {}))
    rows = []
    for key, child in properties.items():
        child = _resolve(child, root)
        field = f"{prefix}{key}"
        description = _text(child.get("description", ""))
        rows.append((field, _type(child, root), key in required, description))
        if "properties" in child or "allOf" in child:
            nested = _rows(child, root, f"{field}.")
            if len({(kind, req, text) for _, kind, req, text in nested}) == 1 and not nested[0][3]:
                # Plain same-typed members (the six wrench axes of a metric): one row for all.
                names = ",".join(row[0].removeprefix(f"{field}.") for row in nested)
                nested = [(f"{field}.{{{names}}}", *nested[0][1:])]
            rows += nested
        items = child.get("items")
        if isinstance(items, dict) and "properties" in _resolve(items, root):
            rows += _rows(items, root, f"{field}[].")
    return rows


def schema_section(name: str) -> str:
    """Markdown: the schema's title and description, then its field table."""
    schema = _load(name)
    lines = [
        f"**`{name}.schema.json`**: {_text(schema.get('title', name))}.",
        "",
        _text(schema.get("description", "")),
        "",
        "| field | type | required | meaning |",
        "|---|---|---|---|",
    ]
    for field, kind, required, description in _rows(schema, schema, ""):
        lines.append(f"| `{field}` | {kind} | {'yes' if required else ''} | {description} |")
    return "\n".join(lines)


def on_page_markdown(markdown: str, page, config, files) -> str:
    return _MARKER.sub(lambda match: schema_section(match.group(1)), markdown)
