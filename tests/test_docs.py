"""The documentation holds together (issue 49): docs/benchmarks.md stays short, every citation
of a heading (`docs/<file>.md, "Heading"`) finds that heading in that file, every relative link
and image of README.md and docs/ points to a file, and each benchmark script's section is in the
page it writes. Files are read as text; nothing is imported from the package."""
import ast
import bisect
import glob
import os
import re

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

MAX_BENCHMARKS_LINES = 650

# the scripts that write a section by its heading, and the page each writes
WRITERS = {
    "benchmarks/accuracy/run.py": "docs/benchmarks/accuracy.md",
    "benchmarks/stability/run.py": "docs/benchmarks/stability.md",
    "benchmarks/cost/run.py": "docs/benchmarks.md",
    "benchmarks/liggghts_side_by_side.py": "docs/benchmarks.md",
}

# docs/<file>.md, then a comma or colon, a space or a "(" (not a string's closing quote), an
# optional "section", then "Heading"; more headings may follow as , "Next"
CITATION = re.compile(r'(?<![\w/.])(docs/(?:[\w-]+/)*[\w-]+\.md)(?:[,:][ \t]*|[ \t]+\(?|\()(?:sections?[ \t]+)?'
                      r'"([^"\n]{1,300})"')
NEXT_QUOTE = re.compile(r'[ \t]*,[ \t]*"([^"\n]{1,300})"')
# what starts a continued line of a comment or docstring (its indent, a comment's #)
CONTINUATION = re.compile(r"^[ \t]*(?:#+[ \t]*|//[ \t]*)?")
HEADING = re.compile(r"^(#{1,6})[ \t]+(.+?)[ \t]*#*[ \t]*$")
# a paragraph or list item that opens with a bold title (**Title.** ...) is cited as a heading too
RUN_IN = re.compile(r"^(?:[ \t]*(?:[*-]|\d+\.)[ \t]+)?\*\*([^*\n]+?)\.?\*\*")
LINK = re.compile(r"!?\[[^\]\n]*\]\(([^)\s]+)(?:[ \t]+\"[^\"]*\")?\)")


def _rel(path):
    return os.path.relpath(path, ROOT)


def _read(path):
    with open(path, encoding="utf-8") as fh:
        return fh.read()


def _repo_files(exts):
    out = []
    for dirpath, dirnames, filenames in os.walk(ROOT):
        dirnames[:] = [d for d in dirnames
                       if not d.startswith(".") and d not in ("out", "build", "node_modules", "__pycache__")]
        out += [os.path.join(dirpath, f) for f in filenames if f.endswith(exts)]
    return sorted(out)


def _markdown_files():
    return [os.path.join(ROOT, "README.md")] + sorted(
        glob.glob(os.path.join(ROOT, "docs", "**", "*.md"), recursive=True))


def _without_code_blocks(text):
    """The text with every fenced code block blanked (its lines kept, so line numbers hold)."""
    out, fenced = [], False
    for line in text.split("\n"):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            out.append("")
            continue
        out.append("" if fenced else line)
    return "\n".join(out)


def _norm(s):
    return " ".join(s.replace("`", "").split())


def headings(path):
    """Every heading of a markdown file (any level, outside code blocks) and every bold title that
    opens a paragraph or a list item, whitespace collapsed."""
    hs = []
    for line in _without_code_blocks(_read(path)).split("\n"):
        m = HEADING.match(line) or RUN_IN.match(line)
        if m:
            hs.append(_norm(m.group(m.lastindex)))
    return hs


def citations(path):
    """(line, cited file, quoted heading) for each citation of a heading in a file. A heading
    quoted across a line break (a comment or docstring continued on the next line) is read with
    the lines joined."""
    lines = _read(path).split("\n")
    pieces = [lines[0]] + [CONTINUATION.sub("", line, count=1) for line in lines[1:]]
    starts, pos = [], 0
    for piece in pieces:
        starts.append(pos)
        pos += len(piece) + 1
    flat = " ".join(pieces)
    found = []
    for m in CITATION.finditer(flat):
        line = bisect.bisect_right(starts, m.start())
        quotes, end = [m.group(2)], m.end()
        while (n := NEXT_QUOTE.match(flat, end)):
            quotes.append(n.group(1))
            end = n.end()
        found += [(line, m.group(1), q) for q in quotes]
    return found


def test_benchmarks_page_is_short():
    n = len(_read(os.path.join(ROOT, "docs", "benchmarks.md")).split("\n"))
    assert n <= MAX_BENCHMARKS_LINES, (
        f"docs/benchmarks.md has {n} lines (at most {MAX_BENCHMARKS_LINES}): experiments go to docs/notebook.md, "
        "long generated sections to a page of docs/benchmarks/")


def test_every_cited_heading_is_in_the_cited_file():
    cache, missing = {}, []
    for f in _repo_files((".py", ".md", ".toml", ".sh")):
        if os.path.samefile(f, __file__):
            continue                                  # its own examples
        for line, target, quoted in citations(f):
            path = os.path.join(ROOT, target)
            if not os.path.isfile(path):
                missing.append(f"{_rel(f)}:{line}: {target} does not exist (cited with \"{quoted}\")")
                continue
            if target not in cache:
                cache[target] = headings(path)
            q = _norm(quoted)
            if not any(h.startswith(q) for h in cache[target]):
                missing.append(f"{_rel(f)}:{line}: no heading \"{quoted}\" in {target}")
    assert not missing, "citations whose heading is not in the file named:\n" + "\n".join(missing)


def test_citations_are_found(tmp_path):
    """The reader of citations sees both forms, a heading continued on the next line of a comment,
    and a list of headings; a file name that closes a string is no citation."""
    f = tmp_path / "example.py"
    f.write_text('x = 1  # see docs/benchmarks.md, "Where a\n# step goes": 46-104\n'
                 '"""(docs/models.md "Semi-implicit drag") and docs/notebook.md, "A", "B"."""\n'
                 'help = "do not write docs/benchmarks.md"; y = ("z")\n')
    assert citations(str(f)) == [(1, "docs/benchmarks.md", "Where a step goes"),
                                 (3, "docs/models.md", "Semi-implicit drag"),
                                 (3, "docs/notebook.md", "A"), (3, "docs/notebook.md", "B")]


def test_every_relative_link_and_image_resolves():
    broken = []
    for f in _markdown_files():
        text = _without_code_blocks(_read(f))
        text = re.sub(r"`[^`\n]*`", "", text)       # inline code is not a link
        for m in LINK.finditer(text):
            target = m.group(1).split("#", 1)[0]
            if not target or re.match(r"^[a-z][a-z0-9+.-]*:", target):
                continue                              # an anchor on the page, or a URL
            if not os.path.exists(os.path.normpath(os.path.join(os.path.dirname(f), target))):
                line = text.count("\n", 0, m.start()) + 1
                broken.append(f"{_rel(f)}:{line}: {m.group(0)}")
    assert not broken, "links to files that do not exist:\n" + "\n".join(broken)


def _section_constant(src):
    m = re.search(r'^SECTION = "(## [^"]+)"', src, re.M)
    return m and m.group(1)


def test_each_script_section_is_in_the_page_it_writes():
    for script, page in WRITERS.items():
        src = _read(os.path.join(ROOT, script))
        title = _section_constant(src)
        assert title, f"{script}: no SECTION = \"## ...\""
        assert os.path.basename(page) in src, f"{script} does not name {page}"
        lines = _read(os.path.join(ROOT, page)).split("\n")
        assert lines.count(title) == 1, f"{page} should hold the heading {title!r} once ({script} replaces it)"
        for other in {"docs/benchmarks.md", "docs/benchmarks/accuracy.md", "docs/benchmarks/stability.md",
                      "docs/notebook.md"} - {page}:
            assert title not in _read(os.path.join(ROOT, other)).split("\n"), (
                f"{title!r} is also a heading of {other}: {script} writes {page} only")
    # the coupled split writes its heading by a pattern, into docs/benchmarks.md
    src = _read(os.path.join(ROOT, "benchmarks", "coupling_split.py"))
    m = re.search(r'section = \(f"(## [^\\"]+)\\n', src)
    assert m and '"benchmarks.md"' in src
    assert _read(os.path.join(ROOT, "docs", "benchmarks.md")).split("\n").count(m.group(1)) == 1


def test_work_precision_subsections_are_on_their_page():
    """`benchmarks/accuracy/run.py --only CASE` replaces the subsection "### <title>" of each case."""
    page = headings(os.path.join(ROOT, "docs", "benchmarks", "accuracy.md"))
    titles = []
    for f in ("run.py", "coupled.py"):
        tree = ast.parse(_read(os.path.join(ROOT, "benchmarks", "accuracy", f)))
        for node in ast.walk(tree):
            if isinstance(node, ast.Call) and getattr(node.func, "id", None) == "dict":
                for kw in node.keywords:
                    if kw.arg == "title" and isinstance(kw.value, ast.Constant) and isinstance(kw.value.value, str):
                        titles.append(kw.value.value)
    assert len(titles) >= 12
    missing = [t for t in titles if _norm(t) not in page]
    assert not missing, f"no subsection of docs/benchmarks/accuracy.md for {missing}"
