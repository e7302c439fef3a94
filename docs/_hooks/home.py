"""MkDocs hook (mkdocs.yml, ``hooks:``): the site's home page is the repository's README.md.

The page ``index.md`` is generated from README.md at build time, so the two never drift.
README.md's relative links are written for the repository root: a link into ``docs/`` is
rewritten to the page it names; a link to any other file of the repository (outside the
site) becomes its text and the file's path in the repository.
"""

from __future__ import annotations

import re
from pathlib import Path

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.structure.files import File, Files

LINK = re.compile(r"(?P<image>!?)\[(?P<text>[^\]]*)\]\((?P<target>[^)\s]+)\)")


def _relink(match: re.Match) -> str:
    target = match["target"]
    if re.match(r"[a-z][a-z0-9+.-]*:|#|/", target):  # a URL, an anchor on the page, a site path
        return match[0]
    if target.startswith("docs/"):
        return f"{match['image']}[{match['text']}]({target.removeprefix('docs/')})"
    return f"{match['text']} (`{target}` in the repository)"


def on_files(files: Files, config: MkDocsConfig) -> Files:
    readme = Path(config.config_file_path).parent / "README.md"
    files.append(File.generated(config, "index.md", content=LINK.sub(_relink, readme.read_text(encoding="utf-8"))))
    return files
