# Sourced by the device-machine scripts (benchmarks/gpu_check.sh): where the image lacks Ray or gymnasium,
# install what benchmarks/gpu_wheels.sh put in .whl/ (carried by the call) into /tmp/site; then put the
# repository on PYTHONPATH.
PY=${PYTHON:-python3}
if ! $PY -c "import ray, gymnasium" 2>/dev/null && [ -d .whl ]; then
    mkdir -p /tmp/site
    $PY -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl
    tar -xJf .whl/ray_slim.tar.xz -C /tmp/site
    export PYTHONPATH=/tmp/site
fi
export PYTHONPATH=$PWD${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
