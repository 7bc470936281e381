#!/usr/bin/env bash
# Builds what a lent GPU machine (Python 3.12, torch with CUDA, no network) lacks to run the
# benches, in the git-ignored .whl/ and .gl/ (carried by the device tool; 64 MiB per call in all):
#   .whl/site.tar.xz  anny (code and the data files its cache is built from), roma, trimesh, pyrender
#                     with pyglet, freetype and PyOpenGL, open3d-cpu (without its TF/torch ops,
#                     resources and plotly visualiser), pyinstrument
#   .whl/deb/         libusb (open3d needs it; unpacked under /tmp there, not /)
#   .gl/              the EGL loader packages (the generator renders with pyrender on EGL)
# Then on the device, from the repository root: `bash tools/gpu_bench.sh` (carry .whl and .gl).
#   .whl/sample/      the sample's first 12 frames (what tests/test_cuda.py reads), as the whole
#                     sample (13 MB) does not fit beside the rest: for the call, `git rm -r -q --cached
#                     data_samples` and add /data_samples/ to .git/info/exclude; after it,
#                     `git reset -q -- data_samples` and take the line out again.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=.venv/bin/python
SP=$($PY -c "import anny, pathlib; print(pathlib.Path(anny.__file__).parent.parent)")
grep -qx "/.whl/" .git/info/exclude 2>/dev/null || echo /.whl/ >> .git/info/exclude
grep -qx "/.gl/" .git/info/exclude || echo /.gl/ >> .git/info/exclude
work=$(mktemp -d); site=$work/site; mkdir -p $site .whl/deb .gl
for spec in roma==1.8.0 trimesh==5.2.0 pyrender==0.1.45 pyglet==2.1.19 freetype-py==2.5.1 pyopengl==3.1.10 \
            open3d-cpu==0.20.0 pyinstrument==5.1.3; do
    $PY -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
        --platform manylinux_2_35_x86_64 --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 \
        --platform manylinux2014_x86_64 --platform manylinux1_x86_64 --platform any -d $work/wheels $spec
done
for w in $work/wheels/*.whl; do unzip -q -o $w -d $site; done
rm -rf $site/open3d/open3d_tf_ops.so $site/open3d/open3d_torch_ops.so $site/open3d/resources \
       $site/open3d/examples $site/open3d/labextension $site/open3d/nbextension $site/open3d/agent_skills
$PY - "$site/open3d/visualization/__init__.py" <<'PYEOF'
import sys
path = sys.argv[1]
text = open(path).read()
lines = ["from .draw_plotly import get_plotly_fig", "from .draw_plotly import draw_plotly",
         "from .draw_plotly import draw_plotly_server", "from .to_mitsuba import to_mitsuba"]
for line in lines:
    text = text.replace(line + "\n", "")
text = text.replace("from ._external_visualizer import *\n", "from ._external_visualizer import *\ntry:\n"
                    + "".join(f"    {line}\n" for line in lines) + "except ImportError:  # no plotly there\n    pass\n")
open(path, "w").write(text)
PYEOF
# anny: its code and the data files it reads while it builds its cache (a fresh one, about a minute)
# and our model, found with an audit hook on `open`; its dist-info (it asks for its own version).
OMP_NUM_THREADS=2 $PY - "$work/anny_cache" > $work/anny_files <<'PYEOF'
import os, sys
read = set()
sys.addaudithook(lambda event, args: event == "open" and isinstance(args[0], str) and "/anny/data/" in args[0]
                 and read.add(args[0]))
import torch
from intercap.body_models import load_body_model
load_body_model("anny", device="cpu", dtype=torch.float32, cache_dir=sys.argv[1])
import anny
root = os.path.dirname(os.path.dirname(anny.__file__))
print("\n".join(sorted(os.path.relpath(p, root) for p in read)))
PYEOF
(cd $SP && { find anny -name "*.py"; find anny-*.dist-info -type f; cat $work/anny_files; } | tar cf - -T -) | tar xf - -C $site
find $site -name __pycache__ -prune -exec rm -rf {} +
tar cf - -C $site . | xz -T0 -7 > .whl/site.tar.xz
o='-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64'
mkdir -p /tmp/amd64/partial && apt-get $o update -qq
(cd .whl/deb && apt-get $o download libusb-1.0-0)
(cd .gl && apt-get $o download libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2)
rm -rf .whl/sample $work
(cd tests && ../$PY -c "from pathlib import Path; from conftest import SAMPLE_SESSION, trimmed_copy; \
trimmed_copy(SAMPLE_SESSION, Path('../.whl/sample'), 12)")
du -sh .whl .gl
