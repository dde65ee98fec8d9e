"""The user's documents speak only of what the user has: no word that points
at a working note, a planning document or a conversation the reader never
saw. Scans README.md, CHANGELOG.md and docs/*.md, case-insensitively, and
names each hit as file:line."""
from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

#: Phrases that point at documents a user does not have (split so that this
#: file does not match itself).
PHRASES = ('this ' + 'session', 'the ' + 'issue', 'closing ' + 'note', 'con' + 'tract',
           'FA' + 'CTS.md', 'the ' + 'brief', 'C' + 'EO', 'iss' + r'ue\s*#?\d+')
PATTERN = re.compile(r'\b(%s)\b' % '|'.join(PHRASES), re.IGNORECASE)


def documents() -> list[Path]:
    return [ROOT / 'README.md', ROOT / 'CHANGELOG.md'] + sorted((ROOT / 'docs').glob('*.md'))


def hits(paths) -> list[str]:
    found = []
    for path in paths:
        for number, line in enumerate(path.read_text().splitlines(), 1):
            match = PATTERN.search(line)
            if match:
                name = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
                found.append('%s:%d: %r in %s' % (name, number, match.group(0), line.strip()))
    return found


def test_the_documents_exist():
    for path in documents()[:2]:
        assert path.is_file(), path


def test_no_word_points_at_documents_a_user_lacks():
    found = hits(documents())
    assert found == [], '\n'.join(found)


def test_the_scan_finds_what_it_looks_for(tmp_path):
    sample = tmp_path / 'x.md'
    sample.write_text('fine\nAs agreed in This Session.\nsee iss' + 'ue #22\nthe con'
                      + 'tract says\n')
    assert [h.split(':')[1] for h in hits([sample])] == ['2', '3', '4']


def test_readme_is_short_and_links_to_docs_that_exist():
    """The README is a five-minute read (at most 350 lines); every local page
    it links to exists, but for the pages other parts of the package add."""
    text = (ROOT / 'README.md').read_text()
    assert len(text.splitlines()) <= 350
    for link in re.findall(r'\]\(((?:docs/)?[\w./-]+\.(?:md|png))(?:#[^)]*)?\)', text):
        if link.startswith('http'):
            continue
        assert (ROOT / link).exists() or link in LATER, link


#: Pages the analysis and fault-injection parts of the package provide.
LATER = {'docs/analysis.md', 'docs/faults.md', 'docs/bode.png', 'docs/workspace.png'}


def _slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to '-'."""
    text = re.sub(r'[^\w\- ]', '', heading.strip().lower())
    return text.replace(' ', '-')


def test_links_between_the_documents_land_on_a_heading():
    """Every link from one document to another (or within one), with or
    without an #anchor, reaches a file that exists and a heading it has."""
    broken = []
    for path in documents():
        for target, anchor in re.findall(r'\]\(([\w./-]*\.md|)(?:#([\w-]+))?\)',
                                         path.read_text()):
            dest = (path.parent / target) if target else path
            if not dest.exists():
                if Path(target).name not in {Path(x).name for x in LATER}:
                    broken.append('%s: %s' % (path.relative_to(ROOT), target))
                continue
            if anchor:
                headings = re.findall(r'^#+ (.*)$', dest.read_text(), re.M)
                if anchor not in {_slug(h) for h in headings}:
                    broken.append('%s: %s#%s' % (path.relative_to(ROOT), target, anchor))
    assert broken == [], broken
