#!/usr/bin/env bash
# The main job: install what is missing, then run a small case, render pictures and a short animation.
# A second run replaces the earlier output (--overwrite: only what the tool wrote there).
#   bash scripts/main.sh            -> out/main/...
set -euo pipefail
ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd -P)"
cd "$ROOT"
bash scripts/setup.sh
PY="${PYTHON:-python3}"
OUT="${OUT:-out/main}"
if [ -f openfoam_cases/fluidized_bed_heating/coupling.toml ] && [ "${MAIN_JOB:-coupled}" = coupled ]; then
    "$PY" -m coupling.run run openfoam_cases/fluidized_bed_heating --out "$OUT/fluidized_bed" --end-time "${MAIN_END_TIME:-0.2}" --overwrite
    "$PY" -m dem.cli render "$OUT/fluidized_bed" --png "$OUT/fluidized_bed/render.png" || echo "(render skipped)"
    "$PY" -m coupling.run render "$OUT/fluidized_bed" || echo "(gas render skipped)"
    "$PY" -m coupling.run render "$OUT/fluidized_bed" --animate || echo "(animation skipped)"
    echo "main job done: $OUT/fluidized_bed (coupling.png, render.png, gas_render.png, gas_animation_eps/ with frame_*.png and animation.gif, fluidized_bed_heating.foam + particles.pvd for ParaView, OpenFOAM time folders)"
else
    "$PY" -m dem.cli check examples/settle_box.toml
    "$PY" -m dem.cli run examples/settle_box.toml --out "$OUT/settle_box" --overwrite
    "$PY" -m dem.cli render "$OUT/settle_box" --png "$OUT/settle_box/render.png"
    echo "main job done: $OUT/settle_box (render.png, particles.pvd, history.csv)"
fi
