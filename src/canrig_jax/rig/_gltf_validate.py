"""The Khronos glTF validator (npm package ``gltf-validator``) run on a file through Node.js.

Install it once with ``npm install gltf-validator`` in the repository (``node_modules/`` is
git-ignored; ``nox -s gltf`` does it) or anywhere on ``NODE_PATH``.
"""

import json
import os
import shutil
import subprocess
from pathlib import Path

_SCRIPT = """
const fs = require('fs');
const validator = require(process.argv[1]);
const bytes = new Uint8Array(fs.readFileSync(process.argv[2]));
validator.validateBytes(bytes, {maxIssues: 1000})
  .then((report) => { process.stdout.write(JSON.stringify(report)); })
  .catch((error) => { process.stderr.write(String(error)); process.exit(2); });
"""


def find_gltf_validator() -> tuple[str, Path] | None:
    """(node executable, gltf-validator package folder), or None when either is missing.

    The package is looked for on ``NODE_PATH``, in ``node_modules`` of the current folder and
    of the folders above this source file (the repository's own)."""
    node = shutil.which("node")
    if node is None:
        return None
    roots = [Path(p) for p in os.environ.get("NODE_PATH", "").split(os.pathsep) if p]
    roots.append(Path.cwd() / "node_modules")
    roots += [parent / "node_modules" for parent in Path(__file__).resolve().parents]
    for root in roots:
        package = root / "gltf-validator"
        if (package / "package.json").is_file():
            return node, package
    return None


def validate_gltf(path: str | os.PathLike, *, timeout: float = 300.0) -> dict:
    """The Khronos validator's report on ``path`` (a dict: ``issues.numErrors``,
    ``issues.numWarnings``, ``issues.messages``, ``info``...).

    Raises FileNotFoundError naming ``path`` when the file is missing and RuntimeError when
    Node.js or the ``gltf-validator`` package is not installed (the message says how)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: glTF file {path} not found")
    found = find_gltf_validator()
    if found is None:
        raise RuntimeError(
            "validate_gltf: needs Node.js and the npm package gltf-validator "
            "(run `npm install gltf-validator` in the repository, or `nox -s gltf`)"
        )
    node, package = found
    result = subprocess.run(
        [node, "-e", _SCRIPT, str(package), str(path)],
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    if result.returncode != 0:
        raise RuntimeError(
            f"validate_gltf: the validator failed on {path}: {result.stderr[-2000:]}"
        )
    return json.loads(result.stdout)
