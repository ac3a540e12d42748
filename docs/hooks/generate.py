"""MkDocs hook (mkdocs.yml `hooks:`): the pages generated at build time, never committed.

- reference/cli.md: every command of the `oodrl` app, with its options, defaults and ranges;
- reference/params.md: every key of the params schema, with its type, default and range;
- results/leaderboard.md (its headline) and results/leaderboard-tables.md (every table),
  results/<environment>.md: the committed tables of the suite and of every pipeline.

The environments' pages join the nav's Results section here, so that a new pipeline needs no
edit of mkdocs.yml.
"""

from __future__ import annotations

from pathlib import Path

import reference_pages
import results_pages
from mkdocs.structure.files import File, Files, InclusionLevel

ROOT = Path(__file__).resolve().parents[2]
RESULTS_SECTION = "Results"


def on_config(config):
    for item in config["nav"] or []:
        if isinstance(item, dict) and RESULTS_SECTION in item:
            entries = item[RESULTS_SECTION]
            listed = {next(iter(e.values())) if isinstance(e, dict) else e for e in entries}
            for env in results_pages.environments(ROOT):
                page = f"results/{env.slug}.md"
                if page not in listed:
                    entries.append({env.title: page})
    return config


def _add(files: Files, config, uri: str, *, inclusion=InclusionLevel.UNDEFINED, **source) -> None:
    existing = files.get_file_from_path(uri)
    if existing is not None:  # a stale copy in docs/ never wins over the generated page
        files.remove(existing)
    files.append(File.generated(config, uri, inclusion=inclusion, **source))


def on_files(files: Files, config) -> Files:
    _add(files, config, "reference/cli.md", content=reference_pages.cli_page())
    _add(
        files,
        config,
        "reference/params.md",
        content=reference_pages.params_page(ROOT / "params.yaml"),
    )
    headline, every_table, copies = results_pages.leaderboard_pages(ROOT)
    _add(files, config, "results/leaderboard.md", content=headline)
    _add(
        files,
        config,
        "results/leaderboard-tables.md",
        content=every_table,
        inclusion=InclusionLevel.NOT_IN_NAV,
    )
    for env in results_pages.environments(ROOT):
        page, figures = results_pages.environment_page(ROOT, env)
        _add(files, config, f"results/{env.slug}.md", content=page)
        copies.update(figures)
    for uri, path in copies.items():
        _add(files, config, uri, abs_src_path=str(path))
    return files
