"""Run a notebook's code cells top to bottom in one namespace, in this process, and record what
each cell printed, returned and plotted as nbformat-4 outputs.

    python notebooks/execute.py [--write] [NOTEBOOK ...]     # default: every notebooks/*.ipynb

No Jupyter kernel is needed (the project does not depend on nbclient or ipykernel). Figures are
collected the way Jupyter's inline backend does: on ``plt.show()`` and at the end of each cell,
every open pyplot figure becomes a PNG ``display_data`` output and is closed. A cell's last
expression, if any, becomes its ``execute_result``; warnings are shown (in the cell's stderr),
not raised, as in a kernel. Each notebook runs in a scratch working
folder. The run uses ``JAXLAND_NOTEBOOK_SMALL=1``
(small sizes) and matplotlib's Agg backend; ``--write`` stores the outputs in the notebook
files, which is how the committed notebooks carry their figures. tests/test_notebooks.py runs
every notebook through ``run``.
"""

from __future__ import annotations

import argparse
import ast
import base64
import contextlib
import io
import json
import os
import sys
import tempfile
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent


def _lines(text: str) -> list[str]:
    return text.splitlines(keepends=True)


def _palette(buf: io.BytesIO) -> bytes:
    """The PNG as a 256-colour palette image: a third of the bytes in git, no visible change."""
    from PIL import Image

    buf.seek(0)
    with Image.open(buf) as im:
        q = im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    out = io.BytesIO()
    q.save(out, format="PNG", optimize=True)
    return out.getvalue()


def _figures(outputs: list) -> None:
    import matplotlib.pyplot as plt

    for num in plt.get_fignums():
        fig = plt.figure(num)
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=72, bbox_inches="tight")
        outputs.append({"output_type": "display_data", "metadata": {},
                        "data": {"image/png": base64.b64encode(_palette(buf)).decode(),
                                 "text/plain": [repr(fig)]}})
    plt.close("all")


def _address_repr(value) -> bool:
    """A repr like ``<matplotlib.legend.Legend at 0x7f...>``: not shown (it changes every run)."""
    r = repr(value)
    return r.startswith("<") and " at 0x" in r


def _show_warning(message, category, filename, lineno, file=None, line=None):
    sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


def _stream(outputs: list, name: str, text: str) -> None:
    if text:
        outputs.append({"output_type": "stream", "name": name, "text": _lines(text)})


def run(path: Path, write: bool = False) -> dict:
    """Execute the notebook at ``path``; return it (as a dict) with fresh outputs. A failing
    cell raises, naming the notebook and the cell; nothing is written then."""
    os.environ["JAXLAND_NOTEBOOK_SMALL"] = "1"
    os.environ.setdefault("MPLBACKEND", "Agg")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    nb = json.loads(Path(path).read_text())
    namespace = {"__name__": "__main__"}
    count = 0
    show = plt.show
    try:
        for i, cell in enumerate(nb["cells"]):
            if cell["cell_type"] != "code":
                continue
            count += 1
            outputs: list = []
            src = "".join(cell["source"])
            tree = ast.parse(src, filename=f"{Path(path).name}[cell {i}]")
            last = tree.body.pop() if tree.body and isinstance(tree.body[-1], ast.Expr) else None
            out, err = io.StringIO(), io.StringIO()

            def flush(*_, **__):
                _stream(outputs, "stdout", out.getvalue())
                out.seek(0)
                out.truncate()
                _figures(outputs)

            plt.show = flush
            # warnings are shown, as a kernel shows them, not raised (pytest's filter turns
            # them into errors otherwise)
            with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), \
                    warnings.catch_warnings():
                warnings.simplefilter("default")
                warnings.showwarning = _show_warning
                exec(compile(tree, f"{Path(path).name}[cell {i}]", "exec"), namespace)
                value = (eval(compile(ast.Expression(last.value), f"{Path(path).name}[cell {i}]",
                                      "eval"), namespace) if last is not None else None)
            _stream(outputs, "stdout", out.getvalue())
            _stream(outputs, "stderr", err.getvalue())
            _figures(outputs)
            if value is not None and not _address_repr(value):
                outputs.append({"output_type": "execute_result", "execution_count": count,
                                "metadata": {}, "data": {"text/plain": _lines(repr(value))}})
            cell["outputs"] = outputs
            cell["execution_count"] = count
            cell["source"] = _lines(src)
    finally:
        plt.show = show
        plt.close("all")
    if write:
        Path(path).write_text(json.dumps(nb, indent=1, ensure_ascii=False) + "\n")
    return nb


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--write", action="store_true", help="store the outputs in the notebooks")
    p.add_argument("notebooks", nargs="*", type=Path)
    args = p.parse_args(argv)
    paths = [p.resolve() for p in args.notebooks] or sorted(HERE.glob("*.ipynb"))
    for path in paths:
        with tempfile.TemporaryDirectory() as scratch, contextlib.chdir(scratch):
            nb = run(path, write=args.write)  # files a notebook writes land in scratch
        n_fig = sum(1 for c in nb["cells"] for o in c.get("outputs", [])
                    if "image/png" in o.get("data", {}))
        print(f"{path.name}: ran, {n_fig} figures" + (" (written)" if args.write else ""),
              file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
