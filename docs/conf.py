"""Sphinx configuration of the sb3-pearl documentation (`make docs`: warnings are errors)."""

from __future__ import annotations

import sb3_pearl

project = "sb3-pearl"
author = "sb3-pearl developers"
release = version = sb3_pearl.__version__

root_doc = "README"  # docs/README.md: the page index, as GitHub shows it
extensions = ["myst_parser", "sphinx.ext.autodoc", "sphinx.ext.viewcode"]
source_suffix = {".md": "markdown", ".rst": "restructuredtext"}
exclude_patterns = ["_build"]
myst_heading_anchors = 4  # the pages link to each other's sections by GitHub's heading anchors
autodoc_member_order = "bysource"
autodoc_typehints = "description"
autodoc_default_options = {"show-inheritance": True}
html_theme = "alabaster"
html_title = "sb3-pearl"
