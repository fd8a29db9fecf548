"""Every figure the README states is the one its committed results file holds.

``docs/results/figures.json`` maps each README figure to its source: a JSON file and a key path in it, or a
markdown file and a regular expression, with the format the README writes it in. Each entry is a README
snippet with ``{}`` where its figures go; the snippet, filled from the files, must appear in the README. So
a figure edited by hand in the README, or a results file replaced, fails here. A second test scans the
README's results and speed sections: every number in their tables (but the label column and the paper's
column) and every decimal or percentage in their prose must sit where a mapped figure does, so a figure
added to the README without a source fails too.
"""

from __future__ import annotations

import functools
import json
import math
import re
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
README = REPO_ROOT / "README.md"
MAPPING = REPO_ROOT / "docs" / "results" / "figures.json"
# Sections of the README whose figures must all be mapped, besides the headline figure's caption (the text
# before the first section): the quickstart, the results and the speed table.
CHECKED_SECTIONS = ("Quickstart", "Results", "Measured speed")
NUMBER = re.compile(r"(?<![\w.:/-])-?\d+(?:,\d{3})*(?:\.\d+)?%?")
LINK = re.compile(r"!?\[[^\]]*\]\([^)]*\)")
DECIMAL_OR_PERCENT = re.compile(r"\.\d|%")
LABEL_COLUMN, PAPER_HEADER = 0, "the paper"


@functools.cache
def _load(path: str):
    text = (REPO_ROOT / path).read_text()
    return json.loads(text) if path.endswith(".json") else text


def _lookup(data, key: str):
    """``a/b/[name=x]/c``: dict keys, list indices, or the list item whose field ``name`` equals ``x``."""
    for part in key.split("/"):
        selector = re.fullmatch(r"\[(\w+)=(.+)\]", part)
        if selector:
            field, wanted = selector.groups()
            matches = [item for item in data if str(item.get(field)) == wanted]
            assert len(matches) == 1, f"{key}: {len(matches)} items with {field}={wanted}"
            data = matches[0]
        elif isinstance(data, list):
            data = data[int(part)]
        else:
            assert part in data, f"{key}: no {part!r} in {sorted(data)[:20]}"
            data = data[part]
    return data


def _raw_value(spec: dict, default_file: str | None):
    path = spec.get("file", default_file)
    source = _load(path)
    if "regex" in spec:
        match = re.search(spec["regex"], source, re.MULTILINE)
        assert match, f"{path}: no match for {spec['regex']!r}"
        return float(match.group(1).replace(",", ""))
    keys = spec["key"] if isinstance(spec["key"], list) else [spec["key"]]
    values = [_lookup(source, key) for key in keys]
    values = [sum(v.values()) if isinstance(v, dict) else v for v in values]
    value = sum(values)
    if "times" in spec:
        times = spec["times"]
        value *= times if isinstance(times, (int, float)) else _lookup(source, times)
    return value


def _formatted(spec: dict, default_file: str | None) -> str:
    value = _raw_value(spec, default_file)
    assert isinstance(value, (int, float)) and math.isfinite(value), (
        f"{spec}: {value!r} is not a finite number"
    )
    fmt = spec["format"]
    if fmt == "int":
        assert abs(value - round(value)) < 1e-6, f"{spec}: {value} is not a count"
        return f"{round(value):,}"
    return fmt.format(value)


def _entries() -> list[dict]:
    return json.loads(MAPPING.read_text())["figures"]


def _rendered(entry: dict) -> tuple[str, list[tuple[int, int]]]:
    """The entry's README snippet filled from its files, and where each figure sits in it."""
    parts = entry["readme"].split("{}")
    assert len(parts) - 1 == len(entry["values"]), entry["readme"]
    text, spans = parts[0], []
    for spec, literal in zip(entry["values"], parts[1:], strict=True):
        figure = _formatted(spec, entry.get("file"))
        spans.append((len(text), len(text) + len(figure)))
        text += figure + literal
    return text, spans


def _sections(readme: str) -> dict[str, tuple[int, int]]:
    """Each ``## `` section's title and its span in the README; the text before the first one is titled ""."""
    starts = [(0, "")] + [(m.start(), m.group(1)) for m in re.finditer(r"^## (.+)$", readme, re.MULTILINE)]
    ends = [start for start, _ in starts[1:]] + [len(readme)]
    return {title: (start, end) for (start, title), end in zip(starts, ends, strict=True)}


def _masked(text: str) -> str:
    """``text`` with its links and images blanked out (their paths are names, not figures)."""
    return LINK.sub(lambda m: " " * len(m.group()), text)


def _checked_numbers(readme: str) -> list[tuple[int, str]]:
    """Offsets and text of the numbers that must be mapped figures: in the checked sections, every number
    of a table's body (but the label column and the paper's column), and every decimal or percentage of
    the prose (links and images masked: their paths are names, not figures)."""
    found = []
    for title, (start, end) in _sections(readme).items():
        if title and not title.startswith(CHECKED_SECTIONS):
            continue
        offset, in_code, header = start, False, None
        for line in readme[start:end].splitlines(keepends=True):
            if line.startswith("```") or in_code:
                in_code ^= line.startswith("```")
            elif line.startswith("|"):
                cells = line.rstrip("\n").split("|")[1:-1]
                if header is None:
                    header = [cell.strip() for cell in cells]
                elif not set(line.strip()) <= set("|-: "):
                    cell_start = offset + 1
                    for i, cell in enumerate(cells):
                        if i != LABEL_COLUMN and header[i] != PAPER_HEADER:
                            found += [
                                (cell_start + m.start(), m.group()) for m in NUMBER.finditer(_masked(cell))
                            ]
                        cell_start += len(cell) + 1
            else:
                header = None
                found += [
                    (offset + m.start(), m.group())
                    for m in NUMBER.finditer(_masked(line))
                    if DECIMAL_OR_PERCENT.search(m.group())
                ]
            offset += len(line)
    return found


@pytest.mark.parametrize("entry", _entries(), ids=lambda entry: entry["readme"][:60])
def test_readme_figure_is_the_files(entry):
    text, _ = _rendered(entry)
    assert text in README.read_text(), (
        f"The README should read {text!r} (figures from the committed files); it does not."
    )


def test_every_readme_figure_is_mapped():
    readme = README.read_text()
    covered = set()
    for entry in _entries():
        text, spans = _rendered(entry)
        for match in re.finditer(re.escape(text), readme):
            for begin, end in spans:
                covered.add((match.start() + begin, match.start() + end))
    for name in json.loads(MAPPING.read_text()).get("not_figures", []):
        assert name in readme, f"not_figures lists {name!r}, which the README no longer has"
        for match in re.finditer(re.escape(name), readme):
            covered.update(
                (match.start() + m.start(), match.start() + m.end()) for m in NUMBER.finditer(name)
            )
    unmapped = [
        (readme.count("\n", 0, offset) + 1, number)
        for offset, number in _checked_numbers(readme)
        if (offset, offset + len(number)) not in covered
    ]
    assert not unmapped, f"README figures with no source in {MAPPING.name} (line, figure): {unmapped}"


RESULTS_BUDGET_BYTES = 3 * 1024 * 1024


def test_docs_results_stay_within_3_mb():
    """Only the runs the docs cite are kept, as compact JSON and palette PNGs (``lerobot_suture.plotting``)."""
    files = [p for p in MAPPING.parent.rglob("*") if p.is_file()]
    total = sum(p.stat().st_size for p in files)
    largest = sorted(files, key=lambda p: -p.stat().st_size)[:5]
    assert total <= RESULTS_BUDGET_BYTES, (
        f"docs/results holds {total / 2**20:.2f} MiB, over its 3 MiB budget; the largest files: "
        + ", ".join(f"{p.relative_to(REPO_ROOT)} ({p.stat().st_size // 1024} KiB)" for p in largest)
    )
