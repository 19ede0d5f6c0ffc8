// MathJax 3, shipped with the site (`docs/_hooks/mathjax.py`). It typesets only the
// formulas: the spans of pymdownx.arithmatex on the Markdown pages (`\(...\)`,
// `\[...\]`) and the Markdown cells of the notebook pages (`$...$`, `$$...$$`).
// The page's regions are ignored, and these two kinds of element processed with
// everything inside them (a class that `ignoreHtmlClass` matches turns it off again,
// so it must not match the unclassed `<p>` of a Markdown cell).
window.MathJax = {
  tex: {
    inlineMath: [["\\(", "\\)"], ["$", "$"]],
    displayMath: [["\\[", "\\]"], ["$$", "$$"]],
    processEscapes: true,
    processEnvironments: true,
  },
  options: {
    ignoreHtmlClass: "md-skip|md-header|md-container|md-dialog|tex2jax_ignore",
    processHtmlClass: "arithmatex|jp-RenderedMarkdown",
  },
  svg: {
    fontCache: "global",
  },
};
