"""The README, the docs/ pages and `uabs-train --help` stay true to the code: every
relative link and anchor resolves, every setting they name exists, every benchmark
flag they use exists, and the help lists every config group option with the values
of the command line it is given."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tests.conftest import run_command
from uabs_rl.config import CONF_DIR, PROJECT_ROOT, setting_roles

# the pages these checks own (docs/results/ and docs/bad_inputs.md are generated or
# kept elsewhere)
PAGES = [PROJECT_ROOT / "README.md", *(PROJECT_ROOT / "docs" / f"{n}.md" for n in (
    "model", "configuration", "running", "evaluation", "safety", "performance", "scaling",
    "code", "interop", "tuning"))]
GROUPS = ("scenario", "channel", "masking", "algo", "traces", "experiment")
SECTIONS = ("scenario", "channel", "masking", "algo", "traces", "train")
HELP_FILE = CONF_DIR / "hydra" / "help" / "uabs_train.yaml"


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to '-'."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(page: Path) -> set[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return {slug(h) for h in re.findall(r"^#+ (.+)$", text, flags=re.M)}


def links(page: Path) -> list[str]:
    text = re.sub(r"```.*?```", "", page.read_text(), flags=re.S)
    return re.findall(r"\]\(([^)\s]+)\)", text)


def code_text(page: Path) -> str:
    """The page's code blocks and inline code, where commands and settings are written."""
    text = page.read_text()
    blocks = re.findall(r"```.*?```", text, flags=re.S)
    inline = re.findall(r"`([^`\n]+)`", re.sub(r"```.*?```", "", text, flags=re.S))
    return "\n".join(blocks + inline)


def setting_exists(key: str) -> bool:
    """True if the dotted ``key`` is a setting of RunConfig or a section of them (a
    learner's own settings included)."""
    return any(k == key or k.startswith(key + ".") for k in setting_roles())


def settings_named(text: str) -> set[str]:
    sections = "|".join(SECTIONS)
    keys = re.findall(rf"(?<![\w/.])((?:{sections})(?:\.[a-z_]+)+)", text)
    return {k for k in keys if not k.endswith((".py", ".md", ".yaml", ".png"))}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_relative_links_and_anchors_resolve(page):
    for target in links(page):
        if re.match(r"[a-z]+:", target):  # https:, mailto:
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        assert dest.exists(), f"{page.name}: link to missing {target}"
        if anchor and dest.suffix == ".md":
            assert anchor in anchors(dest), f"{page.name}: no heading #{anchor} in {path}"


@pytest.mark.parametrize("page", [*PAGES, HELP_FILE], ids=lambda p: p.name)
def test_every_setting_named_exists(page):
    text = page.read_text() if page.suffix == ".yaml" else code_text(page)
    named = settings_named(text)
    missing = sorted(k for k in named if not setting_exists(k))
    assert not missing, f"{page.name} names settings RunConfig does not have: {missing}"


COMMANDS = {"uabs-eval": "uabs_rl/cli/evaluate.py", "uabs-report": "uabs_rl/cli/report.py"}


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_commands_and_their_flags_exist(page):
    """``python benchmarks/<x>.py --flag``, ``uabs-eval --flag`` and ``uabs-report
    --flag`` as the pages write them: the script exists and declares the flag."""
    text = code_text(page)
    uses = re.findall(r"python (benchmarks/\w+\.py)([^`\n]*)", text)
    uses += [(COMMANDS[c], args) for c, args in re.findall(
        r"(?<![\w-])(uabs-eval|uabs-report)\b([^`\n#]*)", text)]
    for script, args in uses:
        source = (PROJECT_ROOT / script).read_text()
        for flag in set(re.findall(r"(?<!\S)(--[a-z-]+)", args)) - {"--help"}:
            assert f'"{flag}"' in source, f"{page.name}: {script} has no {flag}"


def render_help(*overrides: str) -> str:
    out = run_command("train", *overrides, "hydra/help=uabs_train", "--help", cwd=PROJECT_ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def test_help_lists_every_group_option_and_shows_the_command_lines_values():
    text = render_help("masking=flat", "scenario.n_uabs=4", "train.episodes=7")
    assert "_schema" not in text  # the ConfigStore's schema names are not options
    assert "${" not in text
    groups = text.split("== Config groups", 1)[1].split("== Main settings", 1)[0]
    for group in (*GROUPS, "hydra/launcher"):
        assert re.search(rf"^  {re.escape(group)} ", groups, flags=re.M), group
        for option in sorted((CONF_DIR / group).glob("*.yaml")):
            assert re.search(rf"\b{option.stem}\b", groups), f"{group}={option.stem}"
    # each group's lines (from its name to the next group's) end in its option chosen
    # on this command line, wherever the description wraps
    lines = dict(re.findall(r"^  ([a-z/]+) +(.*?)(?=^  [a-z/]+ |\Z)", groups,
                            flags=re.M | re.S))
    assert "[flat]" in lines["masking"] and "[uma]" in lines["channel"]
    assert "[paper]" in lines["obs"] and "[dqn3]" in lines["algo"]
    assert "M, the agents [4]" in text
    assert "training episodes [7]" in text
    listed = re.findall(r"^  ([a-z_]+(?:\.[a-z_]+)*)  ",
                        text.split("== Main settings", 1)[1].split("== Examples", 1)[0],
                        flags=re.M)
    assert len(listed) >= 20
    assert all(setting_exists(k) for k in listed), [k for k in listed if not setting_exists(k)]


def test_uabs_traces_help_says_what_it_does_and_lists_its_options():
    out = run_command("traces", "scenario=bologna", "split=test", "--help", cwd=PROJECT_ROOT)
    assert out.returncode == 0, out.stderr[-2000:]
    text = out.stdout
    assert text.startswith("uabs-traces: run SUMO once and cache") and "${" not in text
    assert "powered by Hydra" not in text  # not Hydra's generic page
    groups = text.split("== Config groups", 1)[1].split("== Settings", 1)[0]
    for group in ("scenario", "traces", "experiment"):
        for option in sorted((CONF_DIR / group).glob("*.yaml")):
            assert re.search(rf"\b{option.stem}\b", groups), f"{group}={option.stem}"
    assert "[bologna]" in groups and "train | eval | test | all [test]" in text
    listed = re.findall(r"^  ([a-z_]+(?:\.[a-z_]+)*)  ",
                        text.split("== Settings", 1)[1].split("== Examples", 1)[0],
                        flags=re.M)
    assert len(listed) >= 8
    assert all(k == "split" or setting_exists(k) for k in listed), listed


def test_every_test_that_bad_inputs_md_names_exists():
    text = (PROJECT_ROOT / "docs" / "bad_inputs.md").read_text()
    named = set(re.findall(r"(test_\w+\.py)::(test_\w+)", text))
    assert len(named) > 50
    missing = [f"{f}::{t}" for f, t in sorted(named)
               if not re.search(rf"^def {t}\(", (PROJECT_ROOT / "tests" / f).read_text(),
                                re.MULTILINE)]
    assert not missing


SNIPPET_PAGES = [PROJECT_ROOT / "README.md", PROJECT_ROOT / "sumo" / "README.md",
                 *sorted((PROJECT_ROOT / "docs").rglob("*.md"))]
PYTHON_FENCES = {"python", "py", "python3", "pycon"}
# a fence info string with this word marks a Python block the test skips knowingly (one
# that needs a trained run or long work); say why in the text beside it
NO_RUN = "no-run"


def fences(page: Path) -> list[tuple[int, str, str]]:
    """Every fenced block of ``page``: ``(line of its opening fence, info string, code)``."""
    found, lines, start = [], page.read_text().splitlines(keepends=True), None
    for n, line in enumerate(lines, 1):
        fence = re.match(r"\s*(```+|~~~+)(.*)$", line)
        if fence and start is None:
            start, marker, info, body = n, fence.group(1), fence.group(2).strip(), []
        elif start is not None and line.strip() == marker:
            found.append((start, info, "".join(body)))
            start = None
        elif start is not None:
            body.append(line)
    assert start is None, f"{page.name}: the fence of line {start} is never closed"
    return found


SNIPPETS = [(page, line, info, code) for page in SNIPPET_PAGES if page.is_file()
            for line, info, code in fences(page)
            if info.split()[:1] and info.split()[0].lower() in PYTHON_FENCES]


def test_the_pages_python_blocks_are_found():
    """The README's and docs' Python blocks are the ones the next test runs: every fence
    has a language (so no Python hides in an unlabelled block), and the known examples
    are among them."""
    unlabelled = [f"{p.relative_to(PROJECT_ROOT)}:{line}" for p in SNIPPET_PAGES
                  if p.is_file() for line, info, _ in fences(p) if not info]
    assert not unlabelled, f"fences without a language: {unlabelled}"
    named = {(p.name, code.split("\n", 1)[0]) for p, _, _, code in SNIPPETS}
    assert ("code.md", "from uabs_rl.config import compose") in named
    assert ("interop.md", "from uabs_rl.config import compose") in named


@pytest.mark.parametrize("page, line, info, code", SNIPPETS,
                         ids=[f"{p.relative_to(PROJECT_ROOT)}:{n}" for p, n, _, _ in SNIPPETS])
def test_every_python_snippet_of_the_docs_runs(page, line, info, code, trace_cache,
                                              monkeypatch, tmp_path):
    """Every Python block of the README and docs/ runs as written (in a scratch folder,
    with the tests' trace cache), except those marked ``no-run``."""
    if NO_RUN in info.split():
        pytest.skip(f"{page.name}:{line} is marked {NO_RUN}")
    if info.split()[0].lower() == "pycon":  # a console session: its input lines
        code = "\n".join(s[4:] for s in code.splitlines() if s.startswith((">>> ", "... ")))
    monkeypatch.setenv("UABS_RL_CACHE", str(trace_cache.parent))
    monkeypatch.chdir(tmp_path)
    exec(compile(code, f"{page.name}:{line}", "exec"), {"__name__": "__snippet__"})
