"""`--help`: every command (and the group) has examples that parse with the real commands and name
files the sample scene has; the group's command list shows each summary whole; the options' help
says what the option means in that command. Nothing here runs a stage."""

from __future__ import annotations

import glob
import re
import shlex

import click
import pytest
from cli_helpers import SAMPLE
from click.testing import CliRunner

from wavelight_cli.help_text import EXAMPLES, SCENE, SUMMARY
from wavelight_cli.main import cli

COMMANDS = sorted(cli.commands)
EXAMPLES_HEADING = re.compile(r"^  Examples\b.*:$")


def _help(*args: str, width: int | None = None) -> str:
    extra = {} if width is None else {"terminal_width": width}
    result = CliRunner().invoke(cli, [*args, "--help"], prog_name="wavelight", **extra)
    assert result.exit_code == 0, result.output
    return result.stdout


def help_examples(text: str) -> list[list[str]]:
    """The example command lines of a --help output, as argv lists (continuation lines joined)."""
    lines = text.splitlines()
    start = next((i for i, ln in enumerate(lines) if EXAMPLES_HEADING.match(ln)), None)
    assert start is not None, f"no Examples block:\n{text}"
    found, current = [], None
    for ln in lines[start + 1:]:
        if ln and not ln.startswith(" "):  # the next section (Options:)
            break
        s = ln.strip()
        if current is not None:
            current += " " + s
        elif s.startswith("wavelight "):
            current = s
        if current is not None and not current.endswith("\\"):
            found.append(shlex.split(current))
            current = None
        elif current is not None:
            current = current[:-1].rstrip()
    assert current is None, f"an example ends in a continuation: {current}"
    return found


def parse(argv: list[str]) -> click.Context:
    """Parse a full `wavelight ...` command line as the CLI would (option types and choices
    converted, required options checked), without running anything."""
    assert argv[0] == "wavelight"
    ctx = cli.make_context("wavelight", argv[1:])
    rest = [*getattr(ctx, "_protected_args", []), *ctx.args]
    name, cmd, args = cli.resolve_command(ctx, rest)
    assert cmd is not None, argv
    return cmd.make_context(name, args, parent=ctx)


@pytest.mark.parametrize("name", ["", *COMMANDS])
def test_help_has_an_examples_block_of_real_command_lines(name):
    text = _help(*([name] if name else []))
    examples = help_examples(text)
    assert 2 <= len(examples) <= 4, examples
    assert len(examples) == len(EXAMPLES[name])
    for argv in examples:
        if name:  # a command's examples run that command
            ctx = parse(argv)
            assert ctx.info_name == name, argv
        assert argv[1:3] == ["-s", SCENE] or argv[1:4] == ["-q", "-s", SCENE], argv
    # every example says what it does, indented under its command line
    block = text[text.index("Examples"):text.index("\nOptions:")]
    for para in block.split("\n\n")[1:]:
        lines = para.splitlines()
        assert lines[0].startswith("    wavelight ") and lines[-1].startswith("        "), para


@pytest.mark.parametrize("name", ["", *COMMANDS])
def test_every_example_parses_and_names_files_the_sample_has(name):
    """An example whose option was renamed, whose value no longer converts (a choice, a number,
    a tuple), or that lost a required option fails to parse here. Paths under spot/ must be in
    the sample scene (outputs under out/ aside); a glob option must match a sample file."""
    for argv in help_examples(_help(*([name] if name else []))):
        ctx = parse(argv)
        for token in argv:
            if token.startswith(f"{SCENE}/") and not token.startswith(f"{SCENE}/out/"):
                assert (SAMPLE / token[len(SCENE) + 1:]).exists(), f"{token} of {argv}: not in {SAMPLE}"
        if ctx.params.get("images"):
            assert glob.glob(str(SAMPLE / ctx.params["images"])), argv


def test_the_examples_and_summaries_cover_every_command():
    assert set(EXAMPLES) == {"", *COMMANDS}
    assert set(SUMMARY) == set(COMMANDS)
    for name, cmd in cli.commands.items():
        assert cmd.short_help == SUMMARY[name], name  # set explicitly: click would cut a long first sentence


@pytest.mark.parametrize("width", [None, 100, 60])
def test_the_group_lists_every_summary_whole(width):
    text = _help(width=width)
    listed = text[text.index("\nCommands:\n") + len("\nCommands:\n"):]
    assert not any(ln.rstrip().endswith("...") for ln in listed.splitlines()), listed
    joined = "".join(listed.split())  # wrapped (at a hyphen, too) in a narrow terminal, but whole
    for name in COMMANDS:
        assert name + "".join(SUMMARY[name].split()) in joined, f"{name}:\n{listed}"
    if width is None:  # the default 80 columns: one line each
        rows = [ln.split(None, 1) for ln in listed.splitlines() if ln.strip()]
        assert {r[0]: r[1] for r in rows} == SUMMARY


@pytest.mark.parametrize("name", ["", *COMMANDS])
def test_help_fits_80_columns(name):
    """The examples are kept as written (click's \\b), so they must fit by themselves."""
    text = _help(*([name] if name else []))
    assert max(len(ln) for ln in text.splitlines()) <= 80


# -- the options' help means what the option does in that command (issue 18) --------------------

def _option_help(command: str, opt: str) -> str:
    cmd = cli.commands[command]
    (param,) = [p for p in cmd.params if opt in p.opts]
    return " ".join((param.help or "").split())


@pytest.mark.parametrize("command", ["render", "relight", "insert", "compare"])
@pytest.mark.parametrize("opt", ["--ks", "--shininess"])
def test_material_help_speaks_of_a_fit_start_only_in_solve(command, opt):
    text = _option_help(command, opt)
    assert "start" not in text and "fit's" not in text, f"{command} {opt}: {text}"
    assert "start" in _option_help("solve", opt)  # solve's options do set the fit's start


@pytest.mark.parametrize("command", sorted(n for n, c in cli.commands.items()
                                           if any("-R" in p.opts for p in c.params)))
def test_resolution_help_does_not_say_hemisphere_for_a_sphere(command):
    """-R's help gives the directions of both modes (3R^2 and 6R^2), not 'the hemisphere' alone."""
    text = _option_help(command, "-R")
    if "hemisphere" in text:
        assert "--sphere" in text and "6R^2" in text, f"{command}: {text}"
    shown = _help(command)
    assert "3R^2 light directions on the hemisphere" not in " ".join(shown.split())


# -- the README's commands section shows the same examples --------------------------------------

def readme_examples() -> list[list[str]]:
    from test_docs import README

    text = README.read_text()
    section = text[text.index("\n## Commands\n"):]
    section = section[:section.index("\n## ", 1)]
    block = section[section.index("```sh\n") + 6:]
    block = block[:block.index("```")]
    return [shlex.split(ln, comments=True) for ln in block.splitlines() if ln.startswith("wavelight ")]


def test_the_readme_commands_are_help_examples_of_every_command():
    examples = readme_examples()
    from_help = {tuple(shlex.split(line)) for cases in EXAMPLES.values() for line, _ in cases}
    for argv in examples:
        assert tuple(argv) in from_help, f"README example not in any --help: {' '.join(argv)}"
        parse(argv)
    assert {parse(argv).info_name for argv in examples} == set(COMMANDS)
