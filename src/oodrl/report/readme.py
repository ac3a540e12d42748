"""Keep README.md's headline table equal to the one the pipeline generated."""

from __future__ import annotations

from pathlib import Path

from oodrl.errors import StoreError

START, END = "<!-- headline:start -->", "<!-- headline:end -->"


def insert_headline(readme: Path, headline: Path) -> None:
    if not headline.is_file():
        raise StoreError(f"{headline}: missing; run `dvc repro render` first.")
    text = readme.read_text()
    if START not in text or END not in text:
        raise StoreError(f"{readme}: no {START} ... {END} markers to replace.")
    before, rest = text.split(START, 1)
    after = rest.split(END, 1)[1]
    table = headline.read_text().strip()
    readme.write_text(f"{before}{START}\n{table}\n{END}{after}")
