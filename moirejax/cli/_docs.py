"""The command-line reference page of the documentation (`docs/cli.md`), generated from the
argument parser so that it never drifts from the commands."""

import argparse

from ._main import build_parser


BEGIN = "<!-- cli-reference:begin (generated from the argument parser by moirejax/cli/_docs.py) -->"
END = "<!-- cli-reference:end -->"


def cli_reference() -> str:
    """Markdown: one section per subcommand with its usage and options."""
    parser = build_parser()
    subparsers = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    lines = [BEGIN]
    for name, sub in subparsers.choices.items():
        help_text = next((a.help for a in subparsers._choices_actions if a.dest == name), "")
        lines += ["", f"### `moirejax {name}`", "", help_text or "", "", "```", sub.format_usage().strip(), ""]
        for action in sub._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            flags = ", ".join(action.option_strings) or action.dest
            meta = "" if action.nargs == 0 else f" {action.metavar or action.dest.upper()}"
            detail = action.help or ""
            if action.choices:
                detail += f" (one of: {', '.join(map(str, action.choices))})"
            if action.default not in (None, False, argparse.SUPPRESS) and action.nargs != 0:
                detail += f" [default: {action.default}]"
            lines.append(f"  {flags}{meta}: {detail}".rstrip())
        lines.append("```")
    lines.append(END)
    return "\n".join(lines)


PAGE = "docs/cli.md"


def update_reference(path: str = PAGE) -> bool:
    """Rewrite the generated section of the reference page; returns whether it changed."""
    with open(path, encoding="utf-8") as f:
        text = f.read()
    start, end = text.index(BEGIN), text.index(END) + len(END)
    new = text[:start] + cli_reference() + text[end:]
    if new != text:
        with open(path, "w", encoding="utf-8") as f:
            f.write(new)
    return new != text


if __name__ == "__main__":
    print("updated" if update_reference() else f"{PAGE} is current")
