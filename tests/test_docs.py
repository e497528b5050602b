"""Every measured number in docs/*.md comes from a results file, and every link between the pages resolves.

A *measurement* is a number followed by the unit of a measured quantity (`UNITS`: ms, s, min, h, m, m/s, cm, mm, km, °,
%, ×, KB, MB, GB, KiB, MiB, GiB, Hz, nats, px, frames/s), written in the prose or tables of a page. It passes when

1. it lies in a generated page (`GENERATED_PAGES`) or between a `<!-- NAME:begin -->` and `<!-- NAME:end -->`
   marker pair (a block a render script writes);
2. it lies in a fenced code block or an inline code span: commands, YAML and literal values, not claims;
3. its paragraph cites a committed results file (`docs/results/NAME.json` or `results/NAME.json`, which must exist).
   A paragraph is a run of non-blank lines; each list item is its own paragraph, and a table counts with the
   paragraph just above it (its caption);
4. its line names a key of the configuration tree or a fixed value of a stage in backticks
   (`smcl.scan.temperature`; a section such as `smcl.converged` counts): it is that setting's value;
5. it is a bound, not a result: preceded by ≤, ≥, <, >, "at most" or "at least" (≤ 30 ms is a target, < 0.5 m a
   test), a confidence level (95 % interval, 95 % ellipse, 95 % bootstrap), or a size (86 × 86 m, 640 × 480 px).

Anything else, such as an accuracy, a time or a rate typed into a page, fails with its page and line: generate it
with a render script, cite the results file it comes from, or delete it. The rule and why it is this one:
docs/decisions.md, "Evaluation".
"""

from __future__ import annotations

import importlib.util
import re
from collections.abc import Iterator
from pathlib import Path

from bimfactor.config import leaf_keys

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"

# Whole pages a tool writes; tests/test_tools.py checks each is current with what it is rendered from.
GENERATED_PAGES = {
    "results.md": "tools/render_results.py",
    "paper-reproduction.md": "tools/paper_ablation.py",
    "config-reference.md": "tools/render_config.py",
}

UNITS = r"ms|s|min|h|km|cm|mm|m/s|m|°|%|×|KB|MB|GB|KiB|MiB|GiB|Hz|nats|px|frames/s"
NUMBER = r"(?<![\w.\-])[−-]?\d+(?:\.\d+)?"
MEASUREMENT = re.compile(rf"({NUMBER})\s?(?:{UNITS})(?![\w/])")
BOUND_BEFORE = re.compile(r"(?:[≤≥<>]|at most|at least)\s*$")
CONFIDENCE_AFTER = re.compile(r"^\s?%\s+(?:bootstrap|interval|ellipse|confidence)")
SIZE = re.compile(rf"{NUMBER}\s?×\s?{NUMBER}(?:\s?(?:{UNITS}))?")
CITATION = re.compile(r"(?:docs/)?results/([\w.\-]+\.json)")
BACKTICKED = re.compile(r"`([^`]+)`")
MARKER = re.compile(r"<!-- ([\w-]+):(begin|end) -->")


def config_names() -> set[str]:
    """Every key of the configuration tree, every fixed value of a stage, and every section above them."""
    spec = importlib.util.spec_from_file_location("render_config", ROOT / "tools/render_config.py")
    render = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(render)
    names = {key for key, _ in leaf_keys()} | {name for name, _, _ in render.fixed_constants()}
    return names | {".".join(n.split(".")[:i]) for n in names for i in range(2, n.count(".") + 1)}


def prose_lines(text: str) -> Iterator[tuple[int, str]]:
    """(line number, line) of the lines outside fenced code and generated blocks, code spans blanked."""
    fenced, block = False, None
    for number, line in enumerate(text.splitlines(), 1):
        marker = MARKER.search(line)
        if marker:
            block = marker.group(1) if marker.group(2) == "begin" else None
            continue
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if fenced or block:
            continue
        yield number, line


def paragraphs(lines: list[tuple[int, str]]) -> Iterator[list[tuple[int, str]]]:
    """Runs of non-blank consecutive lines; a list item starts a new one, a table joins the paragraph above it."""
    runs: list[list[tuple[int, str]]] = []
    previous = 0
    for number, line in lines:
        stripped = line.strip()
        item = re.match(r"^(?:[-*+]|\d+\.)\s", stripped) is not None
        if stripped and (not runs or number != previous + 1 or item):
            runs.append([])
        if stripped:
            runs[-1].append((number, line))
        previous = number if stripped else 0
    for i, run in enumerate(runs):
        starts_table = run[0][1].lstrip().startswith("|")
        if starts_table and i and not runs[i - 1][0][1].lstrip().startswith("|"):
            yield runs[i - 1] + run
        elif not (i + 1 < len(runs) and runs[i + 1][0][1].lstrip().startswith("|") and not starts_table):
            yield run


def offenders(page: Path, names: set[str]) -> list[str]:
    """`page:line: number` for every measurement on the page that passes none of the rules."""
    if page.name in GENERATED_PAGES:
        return []
    found = []
    lines = [(n, line) for n, line in prose_lines(page.read_text())]
    for paragraph in paragraphs(lines):
        cited = [c for _, line in paragraph for c in CITATION.findall(line)]
        if cited and all((DOCS / "results" / c).is_file() for c in cited):
            continue
        for number, line in paragraph:
            keys = {k.rstrip(".*") for k in BACKTICKED.findall(line)}
            if keys & names:
                continue
            prose = BACKTICKED.sub(lambda m: " " * len(m.group(0)), line)
            prose = SIZE.sub(lambda m: " " * len(m.group(0)), prose)
            for match in MEASUREMENT.finditer(prose):
                if BOUND_BEFORE.search(prose[: match.start()]) or CONFIDENCE_AFTER.match(prose[match.end(1) :]):
                    continue
                found.append(f"docs/{page.name}:{number}: {match.group(0).strip()}")
    return found


def test_the_generated_pages_have_their_generators() -> None:
    for page, tool in GENERATED_PAGES.items():
        assert (DOCS / page).is_file() and (ROOT / tool).is_file()


def test_every_measurement_in_the_docs_is_generated_or_cites_a_results_file() -> None:
    names = config_names()
    found = [line for page in sorted(DOCS.glob("*.md")) for line in offenders(page, names)]
    assert not found, f"{len(found)} measured numbers neither generated nor citing docs/results/*.json:\n" + "\n".join(
        found
    )


def test_the_rule_catches_a_typed_measurement(tmp_path: Path) -> None:
    """The rule fails on a hand-typed result and passes the forms it allows."""
    names = {"smcl.scan.temperature", "smcl"}
    page = tmp_path / "page.md"
    page.write_text(
        "The filter step takes 4.6 ms and is 92 % right.\n\n"
        "Within ≤ 30 ms, a 95 % interval, 86 × 86 m, `--set x=0.3 m`.\n\n"
        "The scan term's temperature `smcl.scan.temperature` is 0.3, sigma 0.2 m.\n\n"
        "From docs/results/speed.json: 66.6 ms.\n\n"
        "- a list item at 3.5 m\n- an item citing results/speed.json at 2 m\n\n"
        "<!-- x:begin -->\n12 ms\n<!-- x:end -->\n\n```\n5 ms\n```\n"
    )
    assert offenders(page, names) == ["docs/page.md:1: 4.6 ms", "docs/page.md:1: 92 %", "docs/page.md:9: 3.5 m"]


LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def anchors(page: Path) -> set[str]:
    """GitHub's anchors of a page's headings: lower case, punctuation dropped, spaces as hyphens, repeats numbered."""
    seen: dict[str, int] = {}
    out = set()
    fenced = False
    for line in page.read_text().splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        heading = re.match(r"^#{1,6}\s+(.*)$", line)
        if fenced or not heading:
            continue
        slug = re.sub(r"[^\w\- ]", "", heading.group(1).strip().lower()).replace(" ", "-")
        out.add(slug if slug not in seen else f"{slug}-{seen[slug]}")
        seen[slug] = seen.get(slug, 0) + 1
    return out


def test_every_relative_link_in_the_readme_and_docs_resolves() -> None:
    """A link from README.md or docs/*.md to a file names one that exists, and its #anchor a heading there."""
    broken = []
    for page in [ROOT / "README.md", *sorted(DOCS.glob("*.md"))]:
        text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
        for target in LINK.findall(text):
            if re.match(r"^[a-z]+://|^mailto:", target):
                continue
            path, _, anchor = target.partition("#")
            resolved = (page.parent / path).resolve() if path else page
            if not resolved.exists() or (anchor and resolved.suffix == ".md" and anchor not in anchors(resolved)):
                broken.append(f"{page.relative_to(ROOT)}: {target}")
    assert not broken, "broken links:\n" + "\n".join(broken)
