#!/usr/bin/env bash
# Run the golden-based tests under every numpy BLAS kernel and torch CPU capability this machine can run, one
# setting at a time (docs/development.md, "Before changing a golden"). A one-off developer command, not a CI step:
# each row runs the files again (minutes per row on 2 cores).
#
#   bash scripts/check_kernels.sh                 the golden-based files below
#   bash scripts/check_kernels.sh tests/test_x.py other files instead
#
# Rows: OPENBLAS_CORETYPE=Prescott|Haswell|Zen|SkylakeX with torch's own choice; ATEN_CPU_CAPABILITY=
# default|avx2|avx512 with OpenBLAS's own choice; and one row as an AVX2-only AMD machine runs (Zen kernel, torch
# avx2, numpy's SIMD loops without AVX-512). A kernel the CPU lacks is left out (it would stop on an illegal
# instruction). Each row first prints the kernels that actually ran: OpenBLAS reports its core by name (a forced
# core it does not build maps to the nearest one, e.g. Prescott -> Katmai), torch its capability, numpy its
# highest SIMD level.
set -uo pipefail
REPO=$(cd "$(dirname "$0")/.." && pwd)
PY=${PYTHON:-$REPO/.venv/bin/python}
cd "$REPO"
FILES=("$@")
[ ${#FILES[@]} -gt 0 ] || FILES=(tests/test_import_upstream.py tests/test_upstream_crop.py tests/test_sampling.py
                                 tests/test_score.py tests/test_official_scores.py tests/test_toy_hand.py
                                 tests/test_score_recon.py tests/test_contact_definitions.py)
export PYTHONPATH="$REPO${PYTHONPATH:+:$PYTHONPATH}" PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}

flags=" $(grep -m1 '^flags' /proc/cpuinfo | cut -d: -f2) "
has() { for f in "$@"; do [[ $flags == *" $f "* ]] || return 1; done; }
rows=("OPENBLAS_CORETYPE=Prescott")
has avx2 fma && rows+=("OPENBLAS_CORETYPE=Haswell" "OPENBLAS_CORETYPE=Zen")
has avx512f avx512bw avx512vl avx512dq avx512cd && rows+=("OPENBLAS_CORETYPE=SkylakeX")
rows+=("ATEN_CPU_CAPABILITY=default")
has avx2 fma && rows+=("ATEN_CPU_CAPABILITY=avx2")
has avx512f avx512bw avx512vl avx512dq && rows+=("ATEN_CPU_CAPABILITY=avx512")
amd="OPENBLAS_CORETYPE=Zen ATEN_CPU_CAPABILITY=avx2 NPY_DISABLE_CPU_FEATURES=X86_V4,AVX512_ICL,AVX512_SPR"
has avx2 fma avx512f && rows+=("$amd")

KERNELS_PY=$(cat <<'EOF'
import ctypes, glob, os
import numpy, scipy, torch
from numpy._core._multiarray_umath import __cpu_features__

def corenames():
    try:
        from threadpoolctl import threadpool_info
        return sorted({f"{i['prefix']} {i.get('architecture')}" for i in threadpool_info()
                       if i["internal_api"] == "openblas"})
    except ImportError:  # what threadpoolctl asks too: the loaded OpenBLAS libraries' own report
        out = []
        for mod in (numpy, scipy):
            libs = os.path.join(os.path.dirname(mod.__file__), "..", f"{mod.__name__}.libs")
            for lib in glob.glob(os.path.join(libs, "*openblas*")):
                handle = ctypes.CDLL(lib)
                for sym in ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename", "openblas_get_corename"):
                    if hasattr(handle, sym):
                        getattr(handle, sym).restype = ctypes.c_char_p
                        out.append(f"{mod.__name__} {getattr(handle, sym)().decode()}")
                        break
        return out

simd = max((k for k in ("X86_V2", "X86_V3", "X86_V4") if __cpu_features__.get(k)), default="baseline")
torch_cap = torch.backends.cpu.get_cpu_capability()
print(f"   ran: OpenBLAS ({', '.join(corenames())}); torch {torch_cap}; numpy SIMD {simd}")
EOF
)

passed=() failed=() seen=()
for row in "${rows[@]}"; do
    echo "== $row"
    read -r -a settings <<< "$row"
    run=(env -u OPENBLAS_CORETYPE -u ATEN_CPU_CAPABILITY -u NPY_DISABLE_CPU_FEATURES "${settings[@]}")
    ran=$("${run[@]}" "$PY" -c "$KERNELS_PY") || exit 1
    echo "$ran"
    # a row whose kernels all equal an earlier row's (Zen on an Intel CPU runs Haswell; the machine's own choice)
    # would run the same code again
    if printf '%s\n' "${seen[@]}" | grep -qxF -- "$ran"; then
        echo "   the same kernels as a row above: not run again"
        continue
    fi
    seen+=("$ran")
    "${run[@]}" "$PY" -m pytest -q -x -p no:cacheprovider "${FILES[@]}" 2>&1 | tail -3
    if [ "${PIPESTATUS[0]}" -eq 0 ]; then passed+=("$row"); else failed+=("$row"); fi
done
echo "== passed: ${#passed[@]} of ${#seen[@]} distinct rows"; printf '   %s\n' "${passed[@]}"
[ ${#failed[@]} -eq 0 ] || { echo "== failed: ${#failed[@]}"; printf '   %s\n' "${failed[@]}"; exit 1; }
