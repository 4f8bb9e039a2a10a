"""The docs hold together: README lines stay readable, every results file the docs name exists,
every benchmark script is indexed, and every link to a docs section lands on a heading. Fast: it
reads Markdown and YAML headers only, nothing is trained or imported from drivelab."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results"
MAX_README_LINE = 200
MAX_CONFIG_HEADER = 8

RESULT_EXT = r"(?:json|jsonl|png|csv|md)"
# a path under benchmarks/results/, braces included so that `seed{1,2}` is expanded, not skipped
RESULTS_PATH = re.compile(r"benchmarks/results/[\w./{},-]*?\." + RESULT_EXT + r"\b")
BACKTICKED_FILE = re.compile(r"`([^`\s]+\.(?:json|jsonl|png|csv))`")
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
DOCS_LINK_IN_TEXT = re.compile(r"\bdocs/[\w.-]+\.md#[\w-]+")
# the Markdown that names results files and links to sections: the README, the results docs, the guide
DOCS = ["README.md", "docs/results.md", "docs/history.md", "benchmarks/README.md",
        *sorted(p.relative_to(ROOT).as_posix() for p in (ROOT / "docs" / "guide").glob("*.md"))]


# -- helpers (tested below on bad input, so that the checks can fail) --------------------------


def expand_braces(text: str) -> list[str]:
    """``a{1,2}b`` -> ``a1b``, ``a2b`` (shell-style, nested braces expanded left to right)."""
    match = re.search(r"\{([^{}]*)\}", text)
    if not match:
        return [text]
    out = []
    for option in match.group(1).split(","):
        out += expand_braces(text[: match.start()] + option + text[match.end():])
    return out


def long_lines(text: str, limit: int = MAX_README_LINE) -> list[tuple[int, int]]:
    """(line number, length) of each line longer than ``limit`` characters."""
    return [(n, len(line)) for n, line in enumerate(text.splitlines(), 1) if len(line) > limit]


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a heading: its text (Markdown links and code marks dropped),
    lowercased, every character but letters, digits, ``_``, ``-`` and spaces removed, spaces to ``-``."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = re.sub(r"[`*]", "", text).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def strip_code_blocks(text: str) -> str:
    """The text with fenced code blocks blanked (their lines kept, so line numbers stay)."""
    out, fenced = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
            out.append("")
            continue
        out.append("" if fenced else line)
    return "\n".join(out)


def anchors(text: str) -> set[str]:
    """Every heading anchor of a Markdown text, duplicates numbered as GitHub numbers them."""
    seen: dict[str, int] = {}
    found = set()
    for line in strip_code_blocks(text).splitlines():
        match = HEADING.match(line)
        if not match:
            continue
        anchor = github_anchor(match.group(2))
        if anchor in seen:
            seen[anchor] += 1
            anchor = f"{anchor}-{seen[anchor]}"
        else:
            seen[anchor] = 0
        found.add(anchor)
    return found


def section(text: str, heading: str) -> str:
    """The text of the ``## heading`` section, up to the next heading of level 2 or above."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip() == f"## {heading}")
    end = next((i for i in range(start + 1, len(lines)) if re.match(r"^#{1,2}\s", lines[i])), len(lines))
    return "\n".join(lines[start:end])


def named_results_files(text: str, *, bare_names: bool, base: Path = RESULTS) -> set[str]:
    """Results files a text names, as paths relative to the repository root: every
    ``benchmarks/results/...`` path, and with ``bare_names`` every backticked ``NAME.json`` (or
    ``archive/NAME.json``, ``results/NAME.json`` from benchmarks/), resolved under ``base``."""
    names = set()
    for match in RESULTS_PATH.finditer(text):
        names.update(expand_braces(match.group(0)))
    if bare_names:
        for match in BACKTICKED_FILE.finditer(text):
            for name in expand_braces(match.group(1)):
                if name.startswith("benchmarks/results/"):
                    continue  # counted above
                if name.startswith("results/"):
                    name = name[len("results/"):]
                if "/" in name and not name.startswith("archive/"):
                    continue  # a run's file (RUN/heldout.json), not a results file
                names.add((base / name).relative_to(ROOT).as_posix())
    return names


def missing(paths: set[str], root: Path = ROOT) -> list[str]:
    return sorted(p for p in paths if not (root / p).is_file())


def broken_links(md_path: Path) -> list[str]:
    """Relative links of a Markdown file whose target file, or heading anchor, does not exist."""
    text = strip_code_blocks(md_path.read_text())
    broken = []
    for target in LINK.findall(text):
        if re.match(r"^[a-z]+:", target):  # http:, https:, mailto:
            continue
        path_part, _, anchor = target.partition("#")
        dest = (md_path.parent / path_part).resolve() if path_part else md_path
        if not dest.exists():
            broken.append(target)
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest.read_text()):
            broken.append(target)
    return broken


def broken_docs_refs(text: str, root: Path = ROOT) -> list[str]:
    """``docs/NAME.md#anchor`` written as plain text (config comments): file and anchor must exist."""
    broken = []
    for ref in DOCS_LINK_IN_TEXT.findall(text):
        path, _, anchor = ref.partition("#")
        dest = root / path
        if not dest.is_file() or anchor not in anchors(dest.read_text()):
            broken.append(ref)
    return broken


def config_header(text: str) -> list[str]:
    """The comment lines at the top of a YAML config."""
    header = []
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        header.append(line)
    return header


def lacks_provenance(text: str) -> bool:
    """Whether a benchmark script's text writes JSON to a file (dumps JSON and writes a file) but never
    calls benchmarks/provenance.py's ``provenance(``: its results would not say how they were made."""
    dumps = "json.dump(" in text or "json.dumps(" in text
    writes = "json.dump(" in text or ".write_text(" in text or re.search(r"open\([^)]*['\"][wax]b?['\"]", text)
    return dumps and bool(writes) and "provenance(" not in text


# -- the checks --------------------------------------------------------------------------------


def test_helpers_catch_bad_input(tmp_path):
    assert long_lines("short\n" + "x" * 201 + "\n" + "y" * 200) == [(2, 201)]
    assert expand_braces("a_seed{1,2}_best.json") == ["a_seed1_best.json", "a_seed2_best.json"]
    assert github_anchor("Drive recipe (`configs/drive.yaml`)") == "drive-recipe-configsdriveyaml"
    assert github_anchor("What each lever did in 30 minutes (seed 0)") == "what-each-lever-did-in-30-minutes-seed-0"
    assert anchors("# A\n## Speed\n```\n# not a heading\n```\n### Speed\n") == {"a", "speed", "speed-1"}

    text = "see `no_such_file_xyz.json`, `RUN/heldout.json` and benchmarks/results/nope{1,2}.png"
    names = named_results_files(text, bare_names=True)
    assert names == {"benchmarks/results/no_such_file_xyz.json", "benchmarks/results/nope1.png",
                     "benchmarks/results/nope2.png"}
    assert missing(names) == sorted(names)

    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "a.md").write_text("# Title\n## Real section\n")
    page = tmp_path / "page.md"
    page.write_text("[ok](docs/a.md#real-section) [bad anchor](docs/a.md#gone) [no file](docs/b.md)\n"
                    "```\n[in code](docs/none.md)\n```\n")
    assert broken_links(page) == ["docs/a.md#gone", "docs/b.md"]
    assert broken_docs_refs("# Results: docs/a.md#gone\n# docs/a.md#real-section", root=tmp_path) == ["docs/a.md#gone"]

    assert lacks_provenance("Path(out).write_text(json.dumps(result))")
    assert lacks_provenance("with open(out, 'w') as f:\n    json.dump(result, f)")
    assert not lacks_provenance("Path(out).write_text(json.dumps({**result, **provenance(started)}))")
    assert not lacks_provenance("print(json.dumps(result))\nrows = open(path).read()")  # prints, reads: no file


def test_readme_lines_are_readable():
    assert long_lines((ROOT / "README.md").read_text()) == []


@pytest.mark.parametrize("doc", DOCS)
def test_named_results_files_exist(doc):
    text = (ROOT / doc).read_text()
    if doc == "README.md":  # bare names elsewhere in the README are run files (policy.json, ...)
        names = named_results_files(text, bare_names=False)
        names |= named_results_files(section(text, "Results"), bare_names=True)
    elif doc.startswith("docs/guide/"):  # the guide names run files (state.json, policy.json) bare
        names = named_results_files(text, bare_names=False)
    else:
        names = named_results_files(text, bare_names=True)
    assert missing(names) == []


def test_results_md_names_only_current_files():
    """docs/results.md holds what holds today: its bare names are files in benchmarks/results/
    itself, not archived ones (history.md cites those as archive/NAME)."""
    text = (ROOT / "docs" / "results.md").read_text()
    bare = {m for m in BACKTICKED_FILE.findall(text) if "/" not in m}
    assert bare, "docs/results.md names no results file"
    assert missing({(RESULTS / name).relative_to(ROOT).as_posix() for name in bare}) == []


def test_every_current_results_file_is_cited():
    """A file left in benchmarks/results/ is current, so docs/results.md or benchmarks/README.md
    names it (a PNG through its JSON); superseded files belong in benchmarks/results/archive/."""
    cited = (ROOT / "docs" / "results.md").read_text() + (ROOT / "benchmarks" / "README.md").read_text()
    files = sorted(p for p in RESULTS.iterdir() if p.is_file())
    assert files
    assert [p.name for p in files if p.name not in cited and p.with_suffix(".json").name not in cited] == []


def test_every_results_json_records_its_provenance():
    """A benchmark script that writes JSON merges benchmarks/provenance.py's record into it (those
    that write through training.py's report() get it there)."""
    scripts = sorted(p for p in (ROOT / "benchmarks").glob("*.py") if p.name != "provenance.py")
    assert scripts
    assert [p.name for p in scripts if lacks_provenance(p.read_text())] == []


def test_every_benchmark_script_is_indexed():
    index = (ROOT / "benchmarks" / "README.md").read_text()
    scripts = sorted(p.name for p in (ROOT / "benchmarks").glob("*.py"))
    assert scripts
    assert [name for name in scripts if f"`{name}`" not in index] == []


@pytest.mark.parametrize("doc", DOCS)
def test_links_land_on_existing_files_and_headings(doc):
    assert broken_links(ROOT / doc) == []


def test_readme_links_into_docs_sections():
    """The README's links to docs/*.md#anchor (checked above) are there at all."""
    targets = LINK.findall(strip_code_blocks((ROOT / "README.md").read_text()))
    assert any(re.match(r"docs/[\w.-]+\.md#", t) for t in targets)


@pytest.mark.parametrize("config", sorted(p.name for p in (ROOT / "drivelab" / "configs").glob("*.yaml")))
def test_config_headers_are_short_and_link_to_existing_sections(config):
    header = config_header((ROOT / "drivelab" / "configs" / config).read_text())
    assert len(header) <= MAX_CONFIG_HEADER
    assert broken_docs_refs("\n".join(header)) == []


def test_every_algorithm_has_a_page_on_the_site():
    """docs/algorithms/NAME.md for each file of drivelab/algos/ (mkdocs' strict build checks the nav)."""
    algos = sorted(p.stem for p in (ROOT / "drivelab" / "algos").glob("*.py") if p.stem != "__init__")
    assert algos
    assert [name for name in algos if not (ROOT / "docs" / "algorithms" / f"{name}.md").is_file()] == []
    nav = (ROOT / "mkdocs.yml").read_text()
    assert [name for name in algos if f"algorithms/{name}.md" not in nav] == []
