"""``canrig view``: a local web viewer for rigs and takes (glb files), in any browser.

``ViewerServer`` serves a static page, three.js and one ``.glb`` on 127.0.0.1 only; the page
plays the glb's animation on a timeline, lists its morph targets with sliders and shows
wireframe and the per-vertex colour channel (``COLOR_0``, e.g. an error map) when present.
``screenshot_glb`` renders one frame in headless Chromium (the system's, driven through the
DevTools protocol); ``error_colors`` turns per-vertex errors into a white-to-red ``COLOR_0``
map; ``export_error_glb`` writes a take of meshes with their error over the frames as that map
(an experiment's ``error.glb``), ``save_error_legend`` its colour scale.

three.js is vendored in ``static/three.min.js`` (MIT, ``static/three.LICENSE``): npm ``three``
0.187.0 with its GLTFLoader and OrbitControls bundled into one ES module, rebuilt by::

    npm install three@0.187.0 esbuild@0.28.2
    # entry.js: export {AnimationMixer, Box3, Color, DirectionalLight, DoubleSide, HemisphereLight,
    #   PerspectiveCamera, Scene, Vector3, WebGLRenderer} from 'three';
    #   export {GLTFLoader} from 'three/addons/loaders/GLTFLoader.js';
    #   export {OrbitControls} from 'three/addons/controls/OrbitControls.js';
    npx esbuild entry.js --bundle --format=esm --minify --legal-comments=inline \\
        --outfile=three.min.js
"""

from ._browser import find_chromium
from ._colors import error_colors
from ._error_take import export_error_glb, save_error_legend
from ._glb import inspect_glb
from ._page import screenshot_glb
from ._server import ViewerServer

__all__ = [
    "ViewerServer",
    "error_colors",
    "export_error_glb",
    "find_chromium",
    "inspect_glb",
    "save_error_legend",
    "screenshot_glb",
]
