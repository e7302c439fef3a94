"""MkDocs hook (mkdocs.yml, ``hooks:``): the example notebooks in ``examples/`` as pages.

The notebooks live in the repository's ``examples/`` (where ``make test-all`` executes them),
not under ``docs/``: this hook adds each ``examples/*.ipynb`` to the site's files as it is,
for the mkdocs-jupyter plugin to render with its committed outputs (never re-executed), and
``examples/index.md`` from ``examples/README.md``. It runs before the plugin's own file
handling (event priority), so the plugin sees the notebooks as if they were in ``docs/``.
"""

from __future__ import annotations

import re
from pathlib import Path

from mkdocs.config.defaults import MkDocsConfig
from mkdocs.plugins import event_priority
from mkdocs.structure.files import File, Files

# a link in examples/README.md to a file that is no page (a script) becomes its text and path
SCRIPT_LINK = re.compile(r"\[(?P<text>[^\]]*)\]\((?P<target>(?![a-z][a-z0-9+.-]*:)[^)\s#]+\.py)\)")


@event_priority(100)
def on_files(files: Files, config: MkDocsConfig) -> Files:
    root = Path(config.config_file_path).parent
    for notebook in sorted((root / "examples").glob("*.ipynb")):
        files.append(File(f"examples/{notebook.name}", str(root), config.site_dir, config.use_directory_urls))
    readme = (root / "examples" / "README.md").read_text(encoding="utf-8")
    readme = SCRIPT_LINK.sub(lambda m: f"{m['text']} (`examples/{m['target']}` in the repository)", readme)
    files.append(File.generated(config, "examples/index.md", content=readme))
    return files
