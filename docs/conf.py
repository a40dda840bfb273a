"""Sphinx configuration of warpsim's reference (``sphinx-build -W -b html docs docs/_build/html``)."""

import os
import sys

sys.path.insert(0, os.path.abspath(".."))

import warpsim  # noqa: E402

project = "warpsim"
author = "The warpsim contributors"
copyright = "2026, The warpsim contributors"
release = version = warpsim.__version__

extensions = ["sphinx.ext.autodoc", "sphinx.ext.napoleon", "sphinx.ext.mathjax"]
napoleon_google_docstring = True
napoleon_numpy_docstring = False
napoleon_use_rtype = False
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"members": True, "show-inheritance": True}
autodoc_mock_imports = ["viser", "ray", "matplotlib"]  # optional extras: the reference builds without them
default_role = "code"  # `name` in docstrings reads as code, as in the README

exclude_patterns = ["_build", "*.gif", "*.png"]
html_theme = "alabaster"
html_static_path = []
html_title = f"warpsim {release}"
html_theme_options = {"description": "Physics-based animation solvers as NVIDIA Warp kernels", "page_width": "1100px"}
nitpicky = False


# ---------------------------------------------------------------------------------------------
# warpsim's docstrings are plain text for people reading the source: |v| means a norm, a * b a
# product, and lists continue with hanging indents. After Napoleon has turned the Google-style
# sections into fields, make the rest safe reStructuredText: escape |, lone * and trailing _
# outside ``literals``, and pull hanging continuation lines back to their paragraph's indentation.
import re  # noqa: E402

_LITERAL = re.compile(r"(``.*?``|`[^`]*`)")
_STRUCTURE = re.compile(r"^(:[^:`]+:(\s|$)|\.\. |[-*+] |\d+\. |>>> )")  # a field, not a :role:`x`


def _escape(text):
    parts = _LITERAL.split(text)
    for k in range(0, len(parts), 2):  # even parts are outside literals
        p = parts[k].replace("|", r"\|")
        p = re.sub(r"(?<![*\\])\*(?!\*)", r"\\*", p)  # a lone * (not **bold**, not already escaped)
        p = re.sub(r"(?<=\w)_(?!\w)", r"\\_", p)  # tile_ or key_: not a hyperlink reference
        parts[k] = p
    return "".join(parts)


def _indent(line):
    return len(line) - len(line.lstrip())


def _plain_text_to_rst(app, what, name, obj, options, lines):
    out, literal_indent, anchor = [], None, None
    for line in lines:
        stripped = line.strip()
        if literal_indent is not None:  # inside a literal block: keep verbatim
            if stripped and _indent(line) <= literal_indent:
                literal_indent = None
            else:
                out.append(line)
                continue
        if not stripped:
            out.append(line)
            anchor = None
            continue
        if anchor is None or _STRUCTURE.match(stripped):
            anchor = line  # a paragraph, field or list item starts here
        elif _indent(line) > _indent(anchor) and not _STRUCTURE.match(anchor.strip()):
            line = " " * _indent(anchor) + stripped  # hanging indent: same paragraph
        elif _indent(line) < _indent(anchor):
            anchor = line
        text = line if stripped.startswith((".. ", ">>> ")) else _escape(line)
        out.append(text)
        if stripped.endswith("::"):
            literal_indent = _indent(line)
    lines[:] = out


def setup(app):
    app.connect("autodoc-process-docstring", _plain_text_to_rst, priority=600)  # after Napoleon (500)
