"""The docs stay true to the code.

* Every ``bubble ...`` command shown in docs/*.md and README.md (code blocks and inline code, also
  ``python -m calibrate.cli`` / ``torchrun ... -m calibrate.cli``) names a real subcommand and only
  options that subcommand has; concrete commands (not synopses with ``[ ]`` or ``|``) are parsed in
  full by the real parser, placeholders (``N``, ``KIND@SECONDS``) replaced by sample values.
* The first commands of the user guide's tour run on the simulated bench at small size.
* Every message the code can raise (``InputError``, ``HardwareFault``, ``SafetyViolation``) is
  listed in the troubleshooting section of docs/user_guide.md.
"""

from __future__ import annotations

import ast
import contextlib
import io
import re
import shlex
from pathlib import Path

import pytest

from calibrate.cli import build_parser, main

ROOT = Path(__file__).resolve().parents[1]
DOC_FILES = sorted((ROOT / "docs").glob("*.md")) + [ROOT / "README.md"]
USER_GUIDE = ROOT / "docs" / "user_guide.md"
PACKAGES = ("collect", "calibrate", "trainer", "hw_mocks")
RAISED = {"InputError", "HardwareFault", "SafetyViolation"}
#: How a command starts in the docs; group 1 is what follows the program.
COMMAND_START = re.compile(r"^(?:\$\s+)?(?:\S*bubble|\S*python\S*\s+-m\s+calibrate\.cli|torchrun\s.*?-m\s+calibrate\.cli)\s+(.+)$")
INLINE = re.compile(r"`((?:\S*bubble|\S*python\S*\s+-m\s+calibrate\.cli)\s+[^`]+)`")
SYNOPSIS = re.compile(r"\[|\||\.\.\.|<")
PLACEHOLDER_VALUES = {"KIND@SECONDS": "camera-stall@1.5"}


def _strip_comment(line: str) -> str:
    return re.split(r"\s+#\s", line, maxsplit=1)[0].strip()


def doc_commands() -> list[tuple[str, str, bool]]:
    """(``doc:line``, arguments after the program, from a code block) for every command in the docs."""
    found = []
    for path in DOC_FILES:
        lines = path.read_text().splitlines()
        fenced = False
        current = None
        for number, line in enumerate(lines, 1):
            if line.lstrip().startswith("```"):
                fenced = not fenced
                current = None
                continue
            if fenced:
                match = COMMAND_START.match(_strip_comment(line))
                if match:
                    current = [f"{path.name}:{number}", match.group(1), True]
                    found.append(current)
                elif current is not None and line[:1].isspace() and line.strip():
                    current[1] += " " + _strip_comment(line)  # a synopsis continued on the next line
                else:
                    current = None
            else:
                for text in INLINE.findall(line):
                    match = COMMAND_START.match(text.strip())
                    if match:
                        found.append([f"{path.name}:{number}", match.group(1), False])
    return [tuple(c) for c in found]


COMMANDS = doc_commands()


@pytest.fixture(scope="module")
def parser():
    return build_parser()


def _subparser(parser, tokens: list[str]):
    """The (sub)parser the tokens address and the tokens it parses."""
    for _ in range(3):
        subparsers = [a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction"]
        if not subparsers or not tokens or tokens[0].startswith("-") or tokens[0].isupper():  # or `bubble COMMAND`
            return parser, tokens
        choices = subparsers[0].choices
        alternatives = re.split(r"[|/]", tokens[0])  # prose may show `sim new-sensor|preview`, `train/evaluate`
        assert set(alternatives) <= set(choices), f"unknown subcommand {tokens[0]!r} (have {sorted(choices)})"
        parser, tokens = choices[alternatives[0]], tokens[1:]
    return parser, tokens


def _sample(token: str) -> str:
    if token in PLACEHOLDER_VALUES:
        return PLACEHOLDER_VALUES[token]
    return "1" if re.fullmatch(r"[A-Z][A-Z0-9_]*", token) else token


def test_docs_show_commands():
    names = {c[1].split()[0] for c in COMMANDS}
    assert len(COMMANDS) > 30 and {"sim", "collect", "train", "evaluate", "commission", "tui"} <= names


@pytest.mark.parametrize("where,text,fenced", COMMANDS, ids=[f"{c[0]} {c[1][:40]}" for c in COMMANDS])
def test_doc_command_matches_parser(parser, where, text, fenced):
    tokens = shlex.split(text)
    sub, rest = _subparser(parser, tokens)
    known = set(sub._option_string_actions)
    shown = set(re.findall(r"(?<![\w-])--[a-z][a-z0-9-]*", text))
    assert shown <= known, f"{where}: `bubble {text}` shows {sorted(shown - known)}, not options of `{sub.prog}`"
    if fenced and not SYNOPSIS.search(text):
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            try:
                sub.parse_args([_sample(t) for t in rest])
            except SystemExit as exit_:
                pytest.fail(f"{where}: `bubble {text}` does not parse (exit {exit_.code}): {err.getvalue().strip()}")


def _tour_command(subcommand: str) -> list[str]:
    """The first code-block command of the user guide starting with ``subcommand``."""
    for where, text, fenced in COMMANDS:
        if where.startswith(USER_GUIDE.name) and fenced and text.startswith(subcommand + " "):
            return shlex.split(text)
    raise AssertionError(f"docs/user_guide.md shows no `bubble {subcommand}` command")


def test_user_guide_tour_runs_on_the_simulated_bench(tmp_path, capsys):
    files = {}

    def local(argv: list[str]) -> list[str]:  # the docs' file names -> files in tmp_path
        return [str(files.setdefault(a, tmp_path / a)) if re.fullmatch(r"[\w-]+\.(yaml|png|h5|json)", a) else a
                for a in argv]

    spec = local(_tour_command("sim new-sensor"))
    assert main(spec) == 0 and files["sensor7.yaml"].is_file()
    assert main(local(_tour_command("sim preview"))) == 0 and files["preview.png"].stat().st_size > 1000
    collect = local(_tour_command("collect"))
    # small size: one object, one press (the guide's command records 4 objects x 2 poses)
    k = collect.index("--poses-per-object")
    collect[k + 1] = "1"
    assert main(collect + ["--objects", "box", "--quiet"]) == 0
    capsys.readouterr()
    assert main(local(_tour_command("info"))) == 0
    assert "box" in capsys.readouterr().out


# ---- troubleshooting list -------------------------------------------------------------------------

def _pattern(node: ast.AST) -> str | None:
    """A message expression as text, the parts computed at run time as ``…``."""
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        return "".join(v.value if isinstance(v, ast.Constant) else "…" for v in node.values)
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.Add):
        return (_pattern(node.left) or "…") + (_pattern(node.right) or "…")
    if isinstance(node, (ast.Subscript, ast.Attribute, ast.Call)):  # f"...".splitlines()[0] and the like
        inner = node.value if isinstance(node, (ast.Subscript, ast.Attribute)) else node.func
        return _pattern(inner)
    return None


def raised_messages() -> list[tuple[str, str]]:
    """(``file:line``, message pattern) of every InputError/HardwareFault/SafetyViolation raised in the packages."""
    found = []
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text())):
                if not isinstance(node, ast.Call):
                    continue
                name = getattr(node.func, "id", getattr(node.func, "attr", None))
                if name not in RAISED or not node.args:
                    continue
                message = node.args[1] if name == "HardwareFault" and len(node.args) > 1 else node.args[0]
                pattern = _pattern(message)
                if pattern is not None:
                    found.append((f"{path.relative_to(ROOT)}:{node.lineno}", pattern))
    return found


def test_troubleshooting_lists_every_message():
    guide = USER_GUIDE.read_text().split("## 8. Troubleshooting", 1)[1]
    messages = raised_messages()
    assert len(messages) > 150
    missing = []
    for where, pattern in messages:
        # the longest fixed part of the message must appear in the guide
        fixed = max((part.strip() for part in pattern.split("…")), key=len)
        if len(fixed) >= 6 and fixed not in guide:
            missing.append(f"{where}: {pattern}")
    assert not missing, "add these messages (cause, fix) to docs/user_guide.md section 8:\n" + "\n".join(missing)



def test_the_guide_names_the_optional_fields_of_a_sensor_spec():
    """Was: "every field is required, none extra", though a spec without its defect fields loads."""
    import dataclasses

    from hw_mocks.sensor_spec import SensorSpec

    row = next(line for line in USER_GUIDE.read_text().splitlines() if "missing field '…'" in line)
    optional = [f.name for f in dataclasses.fields(SensorSpec)
                if f.default is not dataclasses.MISSING or f.default_factory is not dataclasses.MISSING]
    assert optional and all(f"`{name}`" in row for name in optional), row


def test_help_gives_the_readme_exit_codes(capsys):
    """``bubble --help`` ends with the exit codes; the README's line gives the same codes and meanings."""
    with pytest.raises(SystemExit) as stop:
        main(["--help"])
    assert stop.value.code == 0
    epilog = " ".join(capsys.readouterr().out.split("exit codes:", 1)[1].split())
    readme = " ".join((ROOT / "README.md").read_text().split("Exit codes:", 1)[1].split("\n\n", 1)[0].split())
    meanings = re.findall(r"\b(\d+) (ok|rejected|bad input|hardware fault|Ctrl-C)", epilog)
    assert [code for code, _ in meanings] == ["0", "1", "2", "3", "130"]
    for code, meaning in meanings:
        assert f"{code} {meaning}" in readme, (code, meaning)
    assert set(re.findall(r"\b\d{3}\b", epilog)) == set(re.findall(r"\b\d{3}\b", readme)) == {"130", "143", "129", "141"}


def test_option_defaults_and_choices_are_the_library_constants(parser):
    """Defaults and choices the command line spells out (to keep ``--help`` free of heavy imports)
    are the constants of the modules that use them."""
    from calibrate.contact_patch import N_POINTS
    from trainer.contact import CONTACT_THRESHOLD_M
    from trainer.inference import RUNTIMES
    from trainer.splits import SPLITS

    def option(command: str, dest: str):
        sub = next(a for a in parser._subparsers._group_actions if a.dest == "command").choices[command]
        return next(a for a in sub._actions if a.dest == dest)

    assert option("pose", "threshold_mm").default == pytest.approx(CONTACT_THRESHOLD_M * 1e3)
    assert option("pose", "points").default == N_POINTS
    assert set(option("train", "split").choices) == set(SPLITS)
    assert set(option("evaluate", "runtime").choices) == set(RUNTIMES)
