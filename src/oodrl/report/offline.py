"""`dvc plots show` without a network: the page template with Vega inlined, and the plot specs.

DVC's default page loads vega, vega-lite and vega-embed from a CDN, so offline its interactive
charts stay blank. `PAGE` is an HTML template for DVC (`.dvc/config`: `plots.html_template`)
that inlines the three libraries — the versions DVC's own page pins (`PINS`), BSD-3-Clause, each
with its licence — and has no `{scripts}` placeholder, so DVC's CDN tags are dropped.

`PLOTS` is the `plots:` section dvc.yaml must hold: the PNG figures, and the CSV files of
`oodrl.report.plots.write_dvc_plot_data` drawn with the Vega-Lite templates in `TEMPLATES_DIR`
(bars from zero, a heatmap, severity curves coloured by detector and faceted by injector), all
rendered as SVG. tests/report/test_offline_plots.py loads the page in headless chromium with
the network cut off and checks that every chart draws.

Upgrading a pin: `npm pack vega@X vega-lite@Y vega-embed@Z`, unpack each into
`DIR/<name>-<version>/`, update `PINS` (versions and the sha256 of the minified builds), then
`python -m oodrl.report.offline DIR` rewrites `PAGE`.
"""

from __future__ import annotations

import hashlib
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

TEMPLATES_DIR = Path(__file__).parent / "vega"
PAGE = TEMPLATES_DIR / "offline_page.html"


@dataclass(frozen=True)
class Library:
    """One pinned npm package whose minified browser build the page inlines."""

    name: str
    version: str
    build: str
    sha256: str

    @property
    def label(self) -> str:
        return f"{self.name}@{self.version}"


#: The versions dvc-render's page loads from the CDN; vega-embed needs vega and vega-lite first.
PINS = (
    Library(
        "vega",
        "5.20.2",
        "build/vega.min.js",
        "4794d0169cb1f3ebad8117fe98ba5bd652dd725905ec0384e832391dbccb03be",
    ),
    Library(
        "vega-lite",
        "5.2.0",
        "build/vega-lite.min.js",
        "d73157451b3978015ab31dacd55ff90d986ab8663fc0abed50f97b3cd90002cb",
    ),
    Library(
        "vega-embed",
        "6.18.2",
        "build/vega-embed.min.js",
        "1ba9826431ddc9805e815ad92acc811c819f2bfd32bda2a128b8c4b5070fab5e",
    ),
)

#: The placeholders DVC fills; a library must not contain them or `</script`.
PLACEHOLDERS = ("{plot_divs}", "{refresh_tag}", "{scripts}")

PAGE_HEAD = """<!DOCTYPE html>
<html>
<head>
<meta charset="utf-8">
{refresh_tag}
<title>oodrl plots</title>
<style>
body { font-family: sans-serif; }
table { border-spacing: 15px; }
</style>
"""

PAGE_BODY = """</head>
<body>
{plot_divs}
</body>
</html>
"""

#: DVC plot definitions: (data file, properties); figures are a directory of PNGs.
PLOTS: tuple[str | dict[str, dict[str, Any]], ...] = (
    "reports/figures",
    {
        "reports/plots/detectors.csv": {
            "template": "src/oodrl/report/vega/bar_from_zero.json",
            "x": "matched_auroc",
            "y": "detector",
            "title": "Mean matched AUROC over anomalies (0.5 = chance)",
            "x_label": "matched AUROC",
            "y_label": "detector",
        }
    },
    {
        "reports/plots/heatmap.csv": {
            "template": "src/oodrl/report/vega/heatmap.json",
            "x": "anomaly",
            "y": "detector",
            "title": "Matched AUROC per detector and anomaly",
            "x_label": "anomaly",
            "y_label": "detector",
        }
    },
    {
        "reports/plots/sweep.csv": {
            "template": "src/oodrl/report/vega/severity_curves.json",
            "x": "severity",
            "y": "matched_auroc",
            "title": "Matched AUROC against severity (dotted: the headline severity)",
            "x_label": "severity σ",
            "y_label": "matched AUROC",
        }
    },
)


def inline_script(library: Library, code: str, licence: str) -> str:
    """A <script> element holding `code`, preceded by its package, version and licence."""
    # DVC replaces its placeholders anywhere in the page, and "</script" would end the element.
    _refuse(library, "code", code, (*PLACEHOLDERS, "</script"))
    _refuse(library, "licence", licence, (*PLACEHOLDERS, "</script", "*/"))
    header = f"/*! {library.label} ({library.build})\n{licence.strip()}\n*/"
    return f"<script>\n{header}\n{code}\n</script>\n"


def _refuse(library: Library, what: str, text: str, forbidden: tuple[str, ...]) -> None:
    found = [f for f in forbidden if f in text]
    if found:
        raise ValueError(f"{library.label}: its {what} contains {found}; it cannot be inlined.")


def build_page(npm_dir: Path) -> str:
    """The page from unpacked npm packages `npm_dir/<name>-<version>/package/`, hashes checked."""
    scripts = []
    for library in PINS:
        package = Path(npm_dir) / f"{library.name}-{library.version}" / "package"
        code = (package / library.build).read_bytes()
        digest = hashlib.sha256(code).hexdigest()
        if digest != library.sha256:
            raise ValueError(f"{library.label}: sha256 {digest}, pinned {library.sha256}.")
        licence = (package / "LICENSE").read_text(encoding="utf-8")
        scripts.append(inline_script(library, code.decode("utf-8"), licence))
    return PAGE_HEAD + "".join(scripts) + PAGE_BODY


def inlined_scripts(page: str) -> list[str]:
    """The code of each inlined library of a page made by `build_page`, in PINS order."""
    parts = page.split("<script>\n")[1:]
    return [part.split("\n*/\n", 1)[1].rsplit("\n</script>", 1)[0] for part in parts]


if __name__ == "__main__":
    PAGE.write_text(build_page(Path(sys.argv[1])), encoding="utf-8")
