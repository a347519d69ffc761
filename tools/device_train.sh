#!/usr/bin/env bash
# Fine-tunes a shipped model on a machine with a CUDA GPU within one call of the device tool (at
# most 10 minutes), from training data prepared beforehand and carried along: that machine has
# PyTorch but no Open3D, so it cannot label meshes, and training needs only the prepared files.
#
# 1. Once, on a machine with o3dvis installed (labels by ray casting; sized to travel):
#      bash tools/device_train.sh --prepare MESHES/train
#    writes carry/ (ignored by git): objects (a tenth of the meshes, 49 152 points each: a model
#    trained on clouds of at most 12 k points lost up to 2 points at 32 k and 81 k), procedural
#    shapes and scenes, about 43 MiB. The tree that travels, tracked files included, must stay
#    under 64 MiB: carry carry/objects and carry/shapes, or carry/objects and carry/scenes.
# 2. On the GPU machine, from the repository root, with the model's folders of carry/ carried:
#      bash tools/device_train.sh MODEL [SECONDS] [INIT]
#    MODEL is default, normals or scene (the normals model half on exact normals, half on those
#    normals="estimate" computes, which the data loader's workers estimate with the shipped
#    default on the CPU); training starts from the shipped weights of MODEL (or
#    from INIT, e.g. a carried checkpoint of an earlier call), stops after SECONDS (default 420)
#    with a checkpoint, and leaves the run (last.safetensors, log.jsonl, config.json) in
#    $OUT/MODEL. Evaluate it here with `o3dvis eval --model FILE` before publishing it (a scene
#    model after `o3dvis fuse`, which fits its fusion with the z-buffer anew: training drops it).
#    The step is bound by kernel launches more than by its clouds: BATCH (clouds a step, default
#    16) and STEPS (the length of the learning-rate schedule, default 4000) size a run to its call.
#    DEVICE=cpu runs the same steps on the CPU (a dry run of the command).
set -euo pipefail
cd "$(dirname "$0")/.."
if [ "${1:-}" = "--prepare" ]; then
    meshes=${2:?give the folder of training meshes}
    rm -rf carry/objects carry/shapes carry/scenes  # prepare keeps finished files: start anew
    mkdir -p carry/object_meshes
    ls "$meshes"/*.* | awk 'NR % 10 == 0' | while read -r f; do ln -sf "$(realpath "$f")" carry/object_meshes/; done
    o3dvis prepare carry/object_meshes carry/objects --points 49152 --views 8 --workers 2
    o3dvis shapes carry/shape_meshes --count 40 --seed 11
    o3dvis prepare carry/shape_meshes carry/shapes --points 12288 --views 8 --workers 2
    o3dvis prepare "$meshes" carry/scenes --scenes 24 --points 16384 --views 8 --seed 21 --workers 2
    rm -rf carry/object_meshes carry/shape_meshes
    du -sh carry
    exit 0
fi
model=${1:?give the model: default, normals or scene}
seconds=${2:-420}
init=${3:-o3dvis/weights/$model.safetensors}
case "$model" in
    default) data="carry/objects carry/shapes"; extra="--max-points 49152" ;;
    normals) data="carry/objects carry/shapes"; extra="--normals --estimated-normals 0.5 --max-points 49152" ;;
    scene) data="carry/scenes carry/objects"; extra="--footprints --max-points 12288" ;;
    *) echo "unknown model $model: default, normals or scene" >&2; exit 2 ;;
esac
out=${OUT:-runs}/$model
export PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}" PYTHONUNBUFFERED=1
python3 setup.py -q build_ext --inplace >/dev/null || echo "no C build: the Python fallbacks run" >&2
workers=$(( $(nproc) > 4 ? $(nproc) - 2 : 0 ))
[ "${DEVICE:-cuda}" = cpu ] || nvidia-smi --query-gpu=name,memory.total --format=csv,noheader || true
# shellcheck disable=SC2086
python3 -m o3dvis train $data --out "$out" --device "${DEVICE:-cuda}" --init "$init" $extra --noise-cues \
    --steps "${STEPS:-4000}" --batch-size "${BATCH:-16}" --lr 5e-4 --min-points 2048 --views 8 \
    --val-every 500 --time-limit "$seconds" --seed 17 --workers "$workers"
rm -f "$out/last_state.pt" "$out/best.safetensors"  # the optimiser state is over what comes back; no val here
ls -l "$out"
