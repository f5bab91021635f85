"""Image-name styles: match a query across tools and find its file (CONVENTIONS §2, image-name styles)."""

from __future__ import annotations

import re
from pathlib import Path

_SEVEN = re.compile(r"^(seq-\d+)[/-](frame-\d+\..*)$")
_CAMBRIDGE = re.compile(r"^(seq\d+)[/_](frame\d+\..*)$")
IMAGE_EXTENSIONS = (".png", ".jpg", ".jpeg")


def _strip_extension(n: str) -> str:
    return n[: -len(n.rsplit(".", 1)[1]) - 1] if n.lower().endswith(IMAGE_EXTENSIONS) else n


def canonical_name(name: str) -> str:
    """A key equal for every style of one frame's name, without its image extension.

    7-Scenes ``seq-01/frame-000000.color.png`` and ``seq-01-frame-000000.color.png`` -> the dashed form;
    Cambridge ``seq2/frame00001.png`` and ``seq2_frame00001.png`` -> the underscore form; 12-Scenes drops
    ``data/``, NeRF ``transforms.json`` ``./`` and ``images/`` (``images/0001.jpg`` and ``0001.png`` match).
    """
    n = name.replace("\\", "/").removeprefix("./")
    for prefix in ("data/", "images/"):
        n = n.removeprefix(prefix)
    m = _SEVEN.match(n)
    if m:
        return _strip_extension(f"{m.group(1)}-{m.group(2)}")
    m = _CAMBRIDGE.match(n)
    if m:
        return _strip_extension(f"{m.group(1)}_{m.group(2)}")
    return _strip_extension(n)


def name_variants(name: str) -> list[str]:
    """Relative paths under which a frame may be stored, the given name first."""
    out = [name]
    n = name.replace("\\", "/")
    for rx, sep in ((_SEVEN, "/"), (_CAMBRIDGE, "/")):
        m = rx.match(n)
        if m:
            out.append(f"{m.group(1)}{sep}{m.group(2)}")
    if not n.startswith("data/") and "/" not in n:
        out.append("data/" + n)
    if n.startswith("data/"):
        out.append(n[5:])
    stems = [_strip_extension(v) for v in out]  # re-encoded frames (transforms.json's .jpg, undistorted .png)
    out += [s + ext for s in stems for ext in IMAGE_EXTENSIONS]
    return list(dict.fromkeys(out))


def resolve_image(name: str, root) -> Path:
    """The file of ``name`` under ``root`` in any name style; FileNotFoundError listing what was tried."""
    root = Path(root)
    tried = []
    for v in name_variants(name):
        p = root / v
        tried.append(str(p))
        if p.is_file():
            return p
    shown = ", ".join(Path(t).relative_to(root).as_posix() for t in tried[:3]) + (", ..." if len(tried) > 3 else "")
    raise FileNotFoundError(f"no image for query {name!r} under {root} (tried {len(tried)} names: {shown})")


def match_names(wanted, available) -> dict[str, str]:
    """Map each name in ``wanted`` to the name in ``available`` with the same canonical key (missing: absent)."""
    index = {canonical_name(a): a for a in available}
    return {w: index[canonical_name(w)] for w in wanted if canonical_name(w) in index}
