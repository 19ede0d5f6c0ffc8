"""MkDocs hook: ship MathJax with the site, so that formulas typeset without a network
(offline, behind a firewall, pages opened from the built folder).

The pages load `_static/mathjax/tex-svg.js`, MathJax 3's TeX-to-SVG component: one
self-contained file (the SVG output needs no web fonts). It is copied into the site
at build time, with MathJax's license beside it, from the `django-static-mathjax`
package (MathJax's release files, with no dependencies; in the `docs` extra, its
version pinned in `constraints.txt`). `_static/mathjax.js` configures it.
"""

import importlib.metadata
import pathlib

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File


PACKAGE = "django-static-mathjax"
DEST = "_static/mathjax"
# file of the package -> name in the site's `_static/mathjax/`
FILES = {
    "mathjax/static/mathjax/es5/tex-svg.js": "tex-svg.js",
    "mathjax/static/mathjax/LICENSE": "LICENSE",
}


def on_files(files, config):
    try:
        dist = importlib.metadata.distribution(PACKAGE)
    except importlib.metadata.PackageNotFoundError as e:
        raise PluginError(
            f"MathJax is not installed (the `{PACKAGE}` package): "
            'pip install -e ".[docs]" -c constraints.txt'
        ) from e
    if not dist.version.startswith("3."):
        raise PluginError(f"MathJax 3 expected, {PACKAGE} is {dist.version}")
    for src, name in FILES.items():
        path = pathlib.Path(dist.locate_file(src))
        if not path.is_file():
            raise PluginError(f"{PACKAGE} {dist.version} has no {src}")
        files.append(File.generated(config, f"{DEST}/{name}", abs_src_path=str(path)))
    return files
