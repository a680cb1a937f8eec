"""Check that every link to an anchor within a built MkDocs site lands on an element with that id.

MkDocs's own check (``validation: anchors``) reads the links of Markdown pages; it does not see
the links that a plugin writes into the HTML, such as the table of contents that mkdocs-jupyter
builds for a notebook from headings whose ids its HTML gives otherwise (a heading with code in
it). This reads the built site instead: every ``href`` with a fragment, on every page, against
the ids of the page it points to.

Usage: ``python .ci/check_anchors.py SITE_DIR``; exit status 1 and one line per broken link.
"""

import html.parser
import pathlib
import posixpath
import sys
import urllib.parse


class _Page(html.parser.HTMLParser):
    """The ids (and ``<a name>``s) of an HTML page and the hrefs of its links, in order."""

    def __init__(self):
        super().__init__(convert_charrefs=True)
        self.ids, self.hrefs = set(), []

    def handle_starttag(self, tag, attrs):
        attrs = dict(attrs)
        for key in ("id", "name") if tag == "a" else ("id",):
            if attrs.get(key):
                self.ids.add(attrs[key])
        if tag == "a" and attrs.get("href"):
            self.hrefs.append(attrs["href"])


def parse(text):
    """``(ids, hrefs)`` of the HTML ``text``."""
    page = _Page()
    page.feed(text)
    page.close()
    return page.ids, page.hrefs


def target(page, href):
    """``(the page a link on ``page`` points to, its fragment)``, both relative to the site's
    root, or None for a link out of the site or one without a fragment."""
    parts = urllib.parse.urlsplit(href)
    if parts.scheme or parts.netloc or not parts.fragment:
        return None
    path = parts.path
    if not path:
        return page, urllib.parse.unquote(parts.fragment)
    if path.startswith("/"):
        return None  # an absolute path depends on where the site is served
    joined = posixpath.join(posixpath.dirname(page), path)
    if path.endswith("/") or not posixpath.splitext(path)[1]:
        joined = posixpath.join(joined, "index.html")
    return posixpath.normpath(joined), urllib.parse.unquote(parts.fragment)


def broken_anchors(site):
    """``[(page, href)]``: the links of the HTML pages under ``site`` whose fragment names no
    element of the page they point to (or whose page is missing)."""
    site = pathlib.Path(site)
    pages = {str(p.relative_to(site).as_posix()): parse(p.read_text(encoding="utf-8"))
             for p in sorted(site.rglob("*.html"))}
    broken = []
    for name, (_, hrefs) in pages.items():
        for href in hrefs:
            found = target(name, href)
            if found is None:
                continue
            page, fragment = found
            if page not in pages or fragment not in pages[page][0]:
                broken.append((name, href))
    return broken


def main(argv):
    if len(argv) != 2:
        print(__doc__.strip().splitlines()[-1], file=sys.stderr)
        return 2
    broken = broken_anchors(argv[1])
    for page, href in broken:
        print(f"{page}: a link to {href!r}, an anchor that the page does not have", file=sys.stderr)
    return 1 if broken else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
