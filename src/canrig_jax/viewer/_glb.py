"""What a binary glTF holds, read from its header and JSON chunk: checked before serving."""

import dataclasses
import json
import os
import struct
from pathlib import Path

_MAGIC = b"glTF"
_JSON_CHUNK = 0x4E4F534A


@dataclasses.dataclass(frozen=True)
class GlbSummary:
    """A ``.glb``'s contents as the viewer shows them (``inspect_glb`` lists the fields)."""

    path: Path
    n_meshes: int
    n_vertices: int
    """POSITION counts summed over every primitive."""
    morph_names: tuple[str, ...]
    """Morph target names of every mesh (``extras.targetNames``, or ``target_i``), each once,
    in mesh order."""
    animations: tuple[str, ...]
    has_colors: bool
    """Whether any primitive has a ``COLOR_0`` attribute."""

    def describe(self) -> str:
        parts = [
            f"{self.n_meshes} mesh{'es' if self.n_meshes != 1 else ''}",
            f"{self.n_vertices} vertices",
            f"{len(self.morph_names)} morph targets",
            f"animation {', '.join(self.animations)}" if self.animations else "no animation",
        ]
        if self.has_colors:
            parts.append("vertex colours (COLOR_0)")
        return f"{self.path.name}: " + ", ".join(parts)


def inspect_glb(path: str | os.PathLike) -> GlbSummary:
    """The summary of the binary glTF 2.0 file ``path``, as the viewer shows it: a
    ``GlbSummary`` with the ``path``, ``n_meshes``, ``n_vertices`` (POSITION counts summed
    over every primitive), ``morph_names`` (every mesh's morph target names,
    ``extras.targetNames`` or ``target_i``, each once, in mesh order), ``animations`` (their
    names), ``has_colors`` (whether any primitive has a ``COLOR_0`` attribute) and
    ``describe()``, the one-line summary ``canrig view`` prints.

    Raises ValueError naming ``path`` when it is missing, not a binary glTF 2.0 file, or holds
    no mesh with triangles to show."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"FILE {path}: not found" + (" (a folder)" if path.is_dir() else ""))
    with open(path, "rb") as f:
        header = f.read(20)
        if len(header) < 20 or header[:4] != _MAGIC:
            raise ValueError(f"FILE {path}: not a binary glTF (.glb) file (no 'glTF' header)")
        version, length, chunk_length, chunk_type = struct.unpack("<4I", header[4:])
        if version != 2:
            raise ValueError(f"FILE {path}: glTF version {version}; the viewer reads glTF 2.0")
        if chunk_type != _JSON_CHUNK or length > path.stat().st_size:
            raise ValueError(f"FILE {path}: a truncated or malformed .glb (bad chunk table)")
        try:
            document = json.loads(f.read(chunk_length))
        except (UnicodeDecodeError, json.JSONDecodeError) as error:
            raise ValueError(f"FILE {path}: the .glb's JSON chunk is not valid: {error}") from None
    if not isinstance(document, dict):
        raise ValueError(f"FILE {path}: the .glb's JSON chunk is not an object")
    accessors = document.get("accessors", [])
    meshes = [m for m in document.get("meshes", []) if m.get("primitives")]
    if not meshes:
        raise ValueError(f"FILE {path}: the .glb holds no mesh to show")
    n_vertices, colors = 0, False
    try:
        for mesh in meshes:
            for primitive in mesh["primitives"]:
                attributes = primitive.get("attributes", {})
                if "POSITION" in attributes:
                    n_vertices += int(accessors[attributes["POSITION"]]["count"])
                colors |= "COLOR_0" in attributes
    except (IndexError, KeyError, TypeError) as error:
        raise ValueError(f"FILE {path}: a mesh refers to a missing accessor ({error})") from None
    if n_vertices == 0:
        raise ValueError(f"FILE {path}: the .glb's meshes have no vertex positions")
    names: dict[str, None] = {}  # every mesh's, in order (an avatar's face meshes share them)
    for mesh in meshes:
        n_targets = len(mesh["primitives"][0].get("targets", []))
        own = mesh.get("extras", {}).get("targetNames") or [f"target_{i}" for i in range(n_targets)]
        names.update(dict.fromkeys(map(str, own[:n_targets] if n_targets else [])))
    animations = tuple(
        str(a.get("name", f"animation_{i}")) for i, a in enumerate(document.get("animations", []))
    )
    return GlbSummary(path, len(meshes), n_vertices, tuple(names), animations, colors)
