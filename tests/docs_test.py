#!/usr/bin/python3
"""Keeps the documentation true: runs the commands it shows and checks the CLI reference.

Usage: docs_test.py --source SOURCE_DIR --build BUILD_DIR [--only FILE.md ...] [--keep]

1. CLI reference: for every subcommand `irmosaic --help` lists, `irmosaic CMD --help` must match
   the section "## irmosaic CMD" of docs/cli.md: every option and positional the help prints is
   in the section's table with the default the help prints, and every option in the table
   exists (no stale ones); every section is a real subcommand.
2. Code blocks in README.md, samples/README.md and docs/*.md:
   - ```sh blocks run with bash (-e -u -o pipefail), ```python blocks with /usr/bin/python3,
     in order, one scratch folder per file (so a later block may use what an earlier one
     wrote), with `irmosaic` on PATH, PYTHONPATH at the built module, and the links `build`,
     `samples`, `docs` to the build and source trees (so `build/cli/irmosaic` and
     `samples/...` work as from the repository root; outputs stay in the scratch folder);
   - a block right after a line `<!-- not run: REASON -->` is not run; it is counted and
     listed with its reason;
   - a block right after `<!-- same as: PATH#NAME -->` must equal the lines between
     `[NAME]` and `[NAME end]` markers in PATH (e.g. the C++ example is the compiled
     consumer sample's code, built and run by the ctest install_consumer);
   - other languages (text, json, csv, cpp without a marker...) are shown, not run;
   - shell commands outside ```sh fences (indented blocks, unlabelled fences starting with a
     known command) are errors: every command shown must be run or marked.
3. Commands quoted inline (`irmosaic CMD --option ...`, `build/bench/NAME ...`) are not run
   (benchmarks take minutes); the command and each irmosaic option must exist.
Exit status 0 when everything holds; 1 otherwise, with each failure explained.
"""
import argparse
import glob
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

COMMAND_WORDS = ("irmosaic", "cmake", "ctest", "gdalinfo", "gdal_translate", "gdalwarp",
                 "python3", "bash", "PYTHONPATH=", "GDAL_DRIVER_PATH=", "build/", "qgis",
                 "apt-get", "sudo", "pytest")
RUN_LANGUAGES = {"sh": "bash", "python": "python"}
BLOCK_TIMEOUT_S = 240


class Block:
    def __init__(self, path, line, language, text, marker):
        self.path, self.line, self.language, self.text, self.marker = (
            path, line, language, text, marker)

    def where(self):
        return "%s:%d" % (self.path, self.line)


def parse_blocks(path, rel):
    """Fenced blocks with the marker comment right before them; indented command lines."""
    blocks, problems = [], []
    lines = open(path, encoding="utf-8").read().split("\n")
    i, marker = 0, None
    previous_blank = True
    while i < len(lines):
        line = lines[i]
        fence = re.match(r"^(\s*)```\s*([A-Za-z0-9_+-]*)\s*$", line)
        if fence:
            indent, language = len(fence.group(1)), fence.group(2)
            body, j = [], i + 1
            while j < len(lines) and not re.match(r"^\s*```\s*$", lines[j]):
                body.append(lines[j][indent:] if lines[j][:indent].strip() == "" else lines[j])
                j += 1
            if j == len(lines):
                problems.append("%s:%d: unclosed ``` fence" % (rel, i + 1))
            text = "\n".join(body)
            blocks.append(Block(rel, i + 1, language, text, marker))
            if not language and first_word_is_command(text):
                problems.append("%s:%d: a command in an unlabelled fence: label it ```sh (run "
                                "by tests/docs_test.py) or ```text for a synopsis" % (rel, i + 1))
            marker = None
            i = j + 1
            previous_blank = False
            continue
        m = re.match(r"^\s*<!--\s*(not run|same as):\s*(.*?)\s*-->\s*$", line)
        if m:
            marker = (m.group(1), m.group(2))
            i += 1
            continue
        # An indented code block: 4 or more spaces after a blank line (also inside lists).
        if previous_blank and line.startswith("    ") and first_word_is_command(line.strip()):
            problems.append("%s:%d: a command in an indented block: put it in a ```sh fence "
                            "(run by tests/docs_test.py) or ```text for a synopsis" % (rel, i + 1))
        if line.strip():
            marker = None
        previous_blank = not line.strip()
        i += 1
    return blocks, problems


def first_word_is_command(text):
    for line in text.split("\n"):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        return stripped.startswith(COMMAND_WORDS)
    return False


def region(source, spec):
    """Lines between [NAME] and [NAME end] markers of a source file, dedented."""
    path, _, name = spec.partition("#")
    lines = open(os.path.join(source, path), encoding="utf-8").read().split("\n")
    start = [k for k, l in enumerate(lines) if l.strip().endswith("[%s]" % name)]
    end = [k for k, l in enumerate(lines) if l.strip().endswith("[%s end]" % name)]
    if len(start) != 1 or len(end) != 1 or end[0] <= start[0]:
        return None
    body = lines[start[0] + 1:end[0]]
    indent = min((len(l) - len(l.lstrip()) for l in body if l.strip()), default=0)
    return "\n".join(l[indent:] for l in body).strip("\n")


# ---------------------------------------------------------------------------------------------
# CLI reference

def help_of(cli, command):
    out = subprocess.run([cli, command, "--help"], capture_output=True, text=True, timeout=60)
    if out.returncode != 0:
        raise RuntimeError("irmosaic %s --help exited %d" % (command, out.returncode))
    options, positionals, section = {}, [], None
    lines = out.stdout.split("\n")
    for k, line in enumerate(lines):
        if line in ("options:", "arguments:"):
            section = line
            continue
        m = re.match(r"^  (\S+)(?: (\S+))?$", line)
        if not m or section is None:
            continue
        name = m.group(1)
        if section == "arguments:":
            positionals.append(name)
            continue
        if name == "--help":
            continue
        text = lines[k + 1] if k + 1 < len(lines) else ""
        default = re.search(r"\(default: (.*?)\)", text)
        options[name] = {"metavar": m.group(2) or "",
                         "default": default.group(1) if default else "",
                         "required": "(required)" in text}
    return options, positionals


def commands_of(cli):
    out = subprocess.run([cli, "--help"], capture_output=True, text=True, timeout=60)
    names, inside = [], False
    for line in out.stdout.split("\n"):
        if line.startswith("commands:"):
            inside = True
            continue
        m = re.match(r"^  ([a-z][a-z0-9_-]*)\s{2,}\S", line)
        if inside and m:
            names.append(m.group(1))
    return names


def cli_sections(text):
    """{command: section text} for the '## irmosaic CMD' headings of docs/cli.md."""
    sections = {}
    parts = re.split(r"^## irmosaic ([a-z][a-z0-9_-]*)\s*$", text, flags=re.M)
    for k in range(1, len(parts), 2):
        sections[parts[k]] = parts[k + 1].split("\n## ")[0]
    return sections


def table_rows(section):
    """(first cell, second cell) of each table row whose first cell names an option."""
    rows = {}
    for line in section.split("\n"):
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 3 or not line.strip().startswith("|"):
            continue
        m = re.match(r"^`(-[^` ]+)(?: [^`]*)?`$", cells[0])
        if m:
            rows[m.group(1)] = cells[1]
    return rows


def check_cli_reference(cli, source):
    problems = []
    path = os.path.join(source, "docs", "cli.md")
    if not os.path.exists(path):
        return ["docs/cli.md is missing"]
    sections = cli_sections(open(path, encoding="utf-8").read())
    commands = commands_of(cli)
    if not commands:
        return ["`irmosaic --help` lists no commands"]
    for extra in sorted(set(sections) - set(commands)):
        problems.append("docs/cli.md documents `irmosaic %s`, which is not a command" % extra)
    for command in commands:
        if command not in sections:
            problems.append("docs/cli.md has no section '## irmosaic %s'" % command)
            continue
        section = sections[command]
        options, positionals = help_of(cli, command)
        rows = table_rows(section)
        for name, spec in options.items():
            if name not in rows:
                problems.append("docs/cli.md, irmosaic %s: option %s (help: %s) is not in the "
                                "options table" % (command, name, spec["metavar"] or "flag"))
                continue
            doc_default = rows[name].strip("`")
            want = spec["default"] or ("required" if spec["required"] else "")
            if doc_default in ("", "-", "—"):
                doc_default = ""
            if doc_default != want:
                problems.append("docs/cli.md, irmosaic %s: option %s default is '%s' in the "
                                "docs but '%s' in --help" % (command, name, doc_default, want))
        for name in rows:
            if name not in options:
                problems.append("docs/cli.md, irmosaic %s: documents option %s, which `irmosaic "
                                "%s --help` does not list" % (command, name, command))
        synopsis = re.search(r"```text\n(.*?)```", section, flags=re.S)
        if not synopsis or ("irmosaic " + command) not in synopsis.group(1):
            problems.append("docs/cli.md, irmosaic %s: no ```text synopsis" % command)
        else:
            for positional in positionals:
                if positional not in synopsis.group(1):
                    problems.append("docs/cli.md, irmosaic %s: positional %s missing from the "
                                    "synopsis" % (command, positional))
    print("cli reference: %d commands checked against --help: %s"
          % (len(commands), ", ".join(commands)))
    return problems


def check_inline_commands(cli, source, files):
    """Commands quoted inline (`irmosaic CMD --opt ...`, `build/...`): the command and each
    option exist. Benchmarks and long runs are quoted this way; they are not run here."""
    problems, checked = [], 0
    commands = set(commands_of(cli))
    helps = {}
    for rel in files:
        text = open(os.path.join(source, rel), encoding="utf-8").read()
        text = re.sub(r"```.*?```", "", text, flags=re.S)  # fenced blocks are run instead
        for span in re.findall(r"`([^`\n]+)`", text):
            words = span.split()
            if len(words) >= 2 and words[0] == "irmosaic" and words[1] in commands:
                if words[1] not in helps:
                    helps[words[1]] = help_of(cli, words[1])[0]
                for word in words[2:]:
                    option = word.split("=")[0]
                    if option.startswith("-") and len(option) > 1 and not option[1].isdigit() \
                            and option not in helps[words[1]] and option != "--help":
                        problems.append("%s: `%s`: irmosaic %s has no option %s"
                                        % (rel, span, words[1], option))
                checked += 1
            elif words and re.match(r"^build/(bench|tests|cli|gdalplugins|python)/\S+$", words[0]):
                kind, name = words[0].split("/")[1], words[0].split("/", 2)[2]
                if kind in ("bench", "tests"):  # one program per bench/[DIR/]NAME.cc
                    exists = bool(glob.glob(os.path.join(source, kind, "**", name + ".cc"),
                                            recursive=True))
                else:
                    exists = bool(glob.glob(os.path.join(os.path.dirname(cli), "..", kind, name)))
                if not exists:
                    problems.append("%s: `%s`: %s is not built by this tree" % (rel, span, words[0]))
                checked += 1
    print("inline commands: %d checked (command and options exist; not run)" % checked)
    return problems


# ---------------------------------------------------------------------------------------------
# Running the blocks

def doc_files(source, only):
    files = ["README.md", os.path.join("samples", "README.md")]
    files += sorted(os.path.join("docs", f) for f in os.listdir(os.path.join(source, "docs"))
                    if f.endswith(".md"))
    if only:
        files = [f for f in files if f in only or os.path.basename(f) in only]
    return files


def scratch_for(root, rel, source, build):
    scratch = os.path.join(root, rel.replace(os.sep, "_").replace(".md", ""))
    os.makedirs(scratch)
    os.symlink(build, os.path.join(scratch, "build"))
    os.symlink(os.path.join(source, "samples"), os.path.join(scratch, "samples"))
    os.symlink(os.path.join(source, "docs"), os.path.join(scratch, "docs"))
    return scratch


def run_block(block, scratch, env):
    if block.language == "sh":
        argv = ["bash", "-e", "-u", "-o", "pipefail", "-c", block.text]
    else:
        argv = ["/usr/bin/python3", "-c", block.text]
    start = time.monotonic()
    try:
        out = subprocess.run(argv, cwd=scratch, env=env, capture_output=True, text=True,
                             timeout=BLOCK_TIMEOUT_S)
        code, output = out.returncode, out.stdout + out.stderr
    except subprocess.TimeoutExpired as e:
        code, output = -1, "timed out after %d s\n%s" % (BLOCK_TIMEOUT_S, e.stdout or "")
    return code, output, time.monotonic() - start


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--source", required=True)
    parser.add_argument("--build", required=True)
    parser.add_argument("--only", nargs="*", default=[], help="only these .md files")
    parser.add_argument("--keep", action="store_true", help="keep the scratch folders")
    args = parser.parse_args()
    source, build = os.path.realpath(args.source), os.path.realpath(args.build)
    cli = os.path.join(build, "cli", "irmosaic")
    problems = [] if args.only else check_cli_reference(cli, source)

    env = dict(os.environ)
    # Debian's tools first (python3 is /usr/bin/python3, the one the module is built for).
    env["PATH"] = os.pathsep.join([os.path.join(build, "cli"), "/usr/bin", "/bin",
                                   env.get("PATH", "")])
    env["PYTHONPATH"] = os.path.join(build, "python")
    env.setdefault("QT_QPA_PLATFORM", "offscreen")
    if not args.only:
        problems += check_inline_commands(cli, source, doc_files(source, []))
    root = tempfile.mkdtemp(prefix="irmosaic_docs_")
    ran, not_run, shown = [], [], 0
    try:
        for rel in doc_files(source, args.only):
            blocks, lint = parse_blocks(os.path.join(source, rel), rel)
            problems += lint
            scratch = None
            for block in blocks:
                if block.marker and block.marker[0] == "same as":
                    expected = region(source, block.marker[1])
                    if expected is None:
                        problems.append("%s: marker region %s not found"
                                        % (block.where(), block.marker[1]))
                    elif expected != block.text.strip("\n"):
                        problems.append("%s: the block differs from %s (copy it again)"
                                        % (block.where(), block.marker[1]))
                    else:
                        ran.append((block, "same as %s" % block.marker[1], 0.0))
                    continue
                if block.language not in RUN_LANGUAGES:
                    shown += 1
                    continue
                if block.marker and block.marker[0] == "not run":
                    if not block.marker[1]:
                        problems.append("%s: 'not run' without a reason" % block.where())
                    not_run.append((block, block.marker[1]))
                    continue
                if scratch is None:
                    scratch = scratch_for(root, rel, source, build)
                code, output, seconds = run_block(block, scratch, env)
                if code != 0:
                    problems.append("%s: the %s block exited %d:\n%s\n--- output ---\n%s"
                                    % (block.where(), block.language, code, block.text,
                                       output[-4000:]))
                ran.append((block, "exit %d" % code, seconds))
    finally:
        if args.keep:
            print("scratch folders kept in", root)
        else:
            shutil.rmtree(root, ignore_errors=True)

    print("\nblocks run or checked (%d):" % len(ran))
    for block, what, seconds in ran:
        print("  %-28s %-6s %-28s %5.1f s" % (block.where(), block.language, what, seconds))
    print("blocks not run (%d):" % len(not_run))
    for block, reason in not_run:
        print("  %-28s %-6s %s" % (block.where(), block.language, reason))
    print("other blocks shown, not commands: %d" % shown)
    if problems:
        print("\n%d problem(s):" % len(problems))
        for p in problems:
            print("- " + p)
        return 1
    print("\ndocs: all commands true")
    return 0


if __name__ == "__main__":
    sys.exit(main())
