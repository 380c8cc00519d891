#!/usr/bin/env bash
# Build ./phm_aoti (main.cpp) against the headers and libraries of the installed torch wheel (libtorch inside it).
#   examples/aoti_cpp/build.sh [OUT]      (g++ >= 9; about a minute: torch's headers are large)
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
out="${1:-$here/phm_aoti}"
read -r inc1 inc2 libdir abi < <(python - <<'PY'
import torch
import torch.utils.cpp_extension as c
print(*c.include_paths(), *c.library_paths(), int(torch._C._GLIBCXX_USE_CXX11_ABI))
PY
)
g++ -std=c++17 -O2 -D_GLIBCXX_USE_CXX11_ABI="$abi" -I"$inc1" -I"$inc2" "$here/main.cpp" -o "$out" \
    -L"$libdir" -Wl,-rpath,"$libdir" -Wl,--no-as-needed -ltorch -ltorch_cpu -lc10
echo "$out"
