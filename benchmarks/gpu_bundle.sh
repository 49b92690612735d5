#!/usr/bin/env bash
# Prepares what a lent GPU machine needs for issue 13's checks (benchmarks/cuda_checks.sh), in two folders that git
# ignores (.git/info/exclude) and the device tool carries: .whl (wheels the machine's image lacks: tyro, kornia and
# their needs, and nerfpipe itself for its entry points) and .gpu (a copy of lego_200x200, blender_lego without most
# of its test split, the synthetic scene in Blender layout, and the scripts setup.sh and run.sh). About 40 MB.
#
#   bash benchmarks/gpu_bundle.sh [DATA]        # DATA: ../shared/data by default
#
# Then, through the device tool: run `bash .gpu/run.sh` with carry [".whl", ".gpu"] (about 4 minutes on an H200; `E2E= bash
# .gpu/run.sh` leaves out the synthetic scene's chain).
# LEGO800=DIR (the 800² stand-in, `python -m benchmarks.lego800 DIR`) also writes .l800: the stand-in with its held-out
# views cut to the 4 the benches score (48 MB: it does not fit one call with .gpu) and .l800/run.sh, issue 18's benches
# of the compact field against the dense one: a second call, `bash .l800/run.sh` with carry [".l800", ".whl"] (about
# 3.5 minutes on an H200, session 58).
# The machine's image has torch, triton, numpy, imageio, safetensors, rich, jaxtyping, matplotlib, scipy and
# scikit-image, but not open3d, pymeshlab, pycolmap or imageio-ffmpeg: the chain of the synthetic scene runs there
# without its render and mesh stages.
set -euo pipefail
cd "$(dirname "$0")/.."
DATA=${1:-../shared/data}
PY=${PY:-.venv/bin/python}
mkdir -p .git/info
for d in /.whl/ /.gpu/ /.l800/; do grep -qxF "$d" .git/info/exclude 2>/dev/null || echo "$d" >>.git/info/exclude; done
rm -rf .whl .gpu && mkdir -p .whl .gpu/lego_200x200 .gpu/blender_lego/test
ver() { "$PY" -c "import importlib.metadata as m; print(m.version('$1'))"; }
"$PY" -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
    "tyro==$(ver tyro)" "kornia==$(ver kornia)" "kornia_rs==$(ver kornia_rs)" "docstring_parser==$(ver docstring_parser)" \
    "typeguard==$(ver typeguard)" "beartype==$(ver beartype)"
"$PY" -m pip wheel -q --no-deps --no-build-isolation -w .whl .
cp "$DATA/lego_200x200/lego_200x200.npz" .gpu/lego_200x200/
cp -r "$DATA/blender_lego/train" "$DATA/blender_lego/val" "$DATA/blender_lego/transforms_train.json" \
    "$DATA/blender_lego/transforms_val.json" .gpu/blender_lego/
"$PY" - "$DATA/blender_lego" <<'PY'
import json, shutil, sys
src = sys.argv[1]
doc = json.load(open(f"{src}/transforms_test.json"))
doc["frames"] = doc["frames"][:4]  # the benches score the val split; the loader wants a test split
for f in doc["frames"]:
    name = f["file_path"].lstrip("./")
    shutil.copy(f"{src}/{name}.png", f".gpu/blender_lego/{name}.png")
json.dump(doc, open(".gpu/blender_lego/transforms_test.json", "w"), indent=1)
PY
"$PY" -c "
from pathlib import Path
from nerfpipe.data.synthetic import SynthConfig, generate
generate(Path('.gpu/synth'), SynthConfig(layout='blender', views=48, seed=0), overwrite=True)"
cat >.gpu/setup.sh <<'SH'
# sourced on the device machine from the repo root: the carried wheels into /tmp/site
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || return 1
export PYTHONPATH=/tmp/site:$PWD PATH=/tmp/site/bin:$PATH PYTHONUNBUFFERED=1 NERFPIPE_DATA=$PWD/.gpu  # the tests' lego_200x200
SH
cat >.gpu/run.sh <<'SH'
#!/usr/bin/env bash
# one device call: issue 13's checks, then the synthetic scene's chain without its render and mesh stages
cd "$(dirname "$0")/.." || exit 1
source .gpu/setup.sh || { echo setup failed; exit 1; }
bash benchmarks/cuda_checks.sh .gpu/lego_200x200/lego_200x200.npz .gpu/blender_lego 2>&1 | tee "$OUT/checks.log"
[ -n "${E2E-1}" ] || exit 0  # E2E= bash .gpu/run.sh: the checks only
echo "== nerfpipe run of the synthetic scene (load, check, train), --time-budget 60"
S0=$SECONDS
timeout 90 nerfpipe run .gpu/synth --out /tmp/e2e --time-budget 60 --stages load,check,train \
    --train.trainer.background white --train.model-options '{"background_field": false}' 2>&1 | tail -12 | tee "$OUT/e2e.log"
echo "wall $((SECONDS - S0)) s"
SH
if [ -n "${LEGO800:-}" ]; then
    rm -rf .l800 && mkdir -p .l800/lego800/val && cp -r "$LEGO800/train" "$LEGO800/transforms_train.json" .l800/lego800/
    "$PY" - "$LEGO800" <<'PY'
import json, shutil, sys
src = sys.argv[1]
for split in ("val", "test"):  # the benches score the first 4 held-out views (evaluation.eval_views)
    doc = json.load(open(f"{src}/transforms_{split}.json"))
    doc["frames"] = doc["frames"][:4]
    for f in doc["frames"]:
        name = f["file_path"].lstrip("./")
        shutil.copy(f"{src}/{name}.png", f".l800/lego800/{name}.png")
    json.dump(doc, open(f".l800/lego800/transforms_{split}.json", "w"), indent=1)
PY
    cat >.l800/run.sh <<'SH'
#!/usr/bin/env bash
# a second device call: issue 18's benches on the 800² stand-in (compact against large stored dense)
cd "$(dirname "$0")/.." || exit 1
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || { echo setup failed; exit 1; }
export PYTHONPATH=/tmp/site:$PWD PATH=/tmp/site/bin:$PATH PYTHONUNBUFFERED=1
ONLY800=1 LEGO800=.l800/lego800 bash benchmarks/cuda_checks.sh x x 2>&1 | tee "$OUT/l800.log"
SH
    du -sh .l800
fi
du -sh .whl .gpu
