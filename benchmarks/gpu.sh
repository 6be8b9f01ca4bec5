#!/usr/bin/env bash
# The GPU measurements of docs/results/gpu.md in one command, on a machine with a CUDA device:
#   bash benchmarks/gpu.sh [OUT_DIR] [PYTHON] [STEP ...]
# (STEPs: machine tests freeway learners control concurrent planner decision_time mbrl_reference
# train_smoke; default: all, in that order).
# Each step has its own time limit and writes OUT_DIR/<step>.log; a failed step does not stop
# the next. mbrl-lib (the last step) is optional: without it that step prints how to install it.
# On a lent machine without a package index (the project's wheels carried in .whl/):
#   python3 -m pip install -q --no-deps --no-index --no-build-isolation --target /tmp/site \
#       .whl/*.whl . && ln -sfn ../recipes mapets_rl/recipes
#   PYTHONPATH=/tmp/site:. PATH=/tmp/site/bin:$PATH bash benchmarks/gpu.sh OUT python3
# (the link: pytest puts the checkout first on the path, where the recipes are not a package).
set -u
out=${1:-gpu_results}
py=${2:-python3}
shift $(($# < 2 ? $# : 2))
wanted=" $* "
mkdir -p "$out"
export PYTHONUNBUFFERED=1 MAPETS_RL_THREADS=1

step() {  # step NAME SECONDS COMMAND...
    local name=$1 limit=$2
    shift 2
    [[ "$wanted" == "  " || "$wanted" == *" $name "* ]] || return 0
    echo "=== $name (limit ${limit}s): $*"
    local t0=$SECONDS
    timeout "$limit" "$@" >"$out/$name.log" 2>&1
    local rc=$?
    tail -n 60 "$out/$name.log"
    echo "=== $name: exit $rc after $((SECONDS - t0)) s"
}

step machine 60 bash -c "nvidia-smi --query-gpu=name,driver_version,memory.total,clocks.max.sm \
    --format=csv; grep -m1 'model name' /proc/cpuinfo; nproc; $py -c 'import torch; \
    print(torch.__version__, torch.version.cuda, torch.cuda.get_device_name(), \
    torch.backends.cpu.get_cpu_capability())'"
step tests 260 "$py" -m pytest -q -p no:cacheprovider tests/planning/test_cuda_graph.py tests/recipes/test_cuda_runs.py \
    tests/planning/test_precision.py tests/envs/test_torch_freeway_cuda.py -k "cuda or graph"
# The batched torch freeway on the GPU: frames/s of 256..65,536 roads beside highway-env and the
# CPU kernel (issue 30), and the model-free learners with roads, networks and replay on the GPU.
step freeway 150 "$py" benchmarks/env_throughput.py --backends freeway-merge --device cuda \
    --roads 1024 8192 65536 --steps 8 --repeats 2
step learners 300 bash -c "set -e; \
    $py benchmarks/learner_throughput.py --device cuda --recipes maddpg --num-envs 8192 \
        --frames 65536 --rounds 2 --threads 1 --schedule openai; \
    $py benchmarks/learner_throughput.py --device cuda --recipes shapley_ac mappo \
        --num-envs 1024 --frames 8192 --rounds 2 --threads 1 --schedule openai; \
    $py benchmarks/learner_throughput.py --device cuda --recipes maddpg --num-envs 1024 \
        --frames 40960 --rounds 3 --threads 1 --schedule openai"
# Issue 32's training stack (epsilon exploration without emergency stops, the model-predictive
# shield, w = 1, individual rewards; MADDPG with one critic per CAV, Shapley AC with the fields
# of the published config freeway-merge/shapley-arm, the three changes with which it finds the
# merge included: uniform coalition sizes, a per-agent layer, member heads) on GPU roads, and on one
# core of this host at the 256 roads of the CPU runs: what a 1M-frame seed of each arm costs.
stack="exploration=epsilon 'exploration_actions=[0, 1, 2]' env_config.shield=true \
    env_config.velocity_weight=1.0 env_config.team_reward=false"
shapley_arm="critic_cells='[64, 64]' logits_reg=0.001 num_permutations=8 shapley_chunk_states=32 \
    shapley_bf16=true coalition_sizes=uniform 'critic_embed_cells=[64]' critic_member_heads=true"
step control 330 bash -c "set -e; \
    $py benchmarks/learner_throughput.py --device cuda --recipes maddpg --num-envs 1024 \
        --frames 40960 --rounds 2 --threads 1 --schedule openai --budget 1000000 $stack \
        critic_share_params=false; \
    $py benchmarks/learner_throughput.py --device cuda --recipes shapley_ac --num-envs 1024 \
        --frames 8192 --rounds 2 --threads 1 --schedule openai --budget 1000000 $stack \
        $shapley_arm; \
    $py benchmarks/learner_throughput.py --recipes maddpg --num-envs 256 --frames 4096 \
        --rounds 2 --threads 1 --schedule openai --budget 1000000 $stack critic_share_params=false; \
    $py benchmarks/learner_throughput.py --recipes shapley_ac --num-envs 256 --frames 2048 \
        --rounds 2 --threads 1 --schedule openai --budget 1000000 $stack $shapley_arm"
# Five seeds of the Shapley arm at once on the one GPU (one process each, as five seeds of a
# paper-budget experiment would run): each process's frames/s; their sum is what the GPU
# delivers when its launch-bound processes overlap.
step concurrent 200 bash -c "logs=\$(mktemp -d); for s in 0 1 2 3 4; do \
    $py benchmarks/learner_throughput.py --device cuda --recipes shapley_ac --num-envs 1024 \
        --frames 8192 --rounds 2 --threads 1 --schedule openai --budget 1000000 seed=\$s $stack \
        $shapley_arm > \$logs/seed\$s.log 2>&1 & done; wait; cat \$logs/seed*.log"
step planner 200 "$py" benchmarks/planner.py --device cuda --configs paper cpu \
    --agents 1 8 22 --dtypes fp32 bf16 --graph --repeats 5 --naive-max-agents 0 --no-separate
step decision_time 150 "$py" benchmarks/decision_time.py --device cuda --decisions 20 \
    --paper-decisions 10 --paper-warmup 1 --methods mapets-paper mapets-paper-graph \
    mapets-cpu mapets-cpu-graph maddpg mappo sac shapley_ac
step mbrl_reference 100 "$py" benchmarks/planner.py --device cuda --configs paper \
    --agents 1 8 --dtypes fp32 --repeats 3 --naive-max-agents 0 --no-separate \
    --reference mbrl-lib
# Every recipe trains, checkpoints and evaluates on the device (tiny budgets; the envs step on
# the CPU): MA-PETS with the CUDA-graph planner, the model-free recipes with their networks.
step train_smoke 200 bash -c "set -e; runs=\$(mktemp -d); \
    mapets-rl train mapets --env figure-eight --run-dir \$runs/mapets preset=cpu episodes=3 \
        random_episodes=1 device=cuda planner.cuda_graph=true env_config.n_cavs=4; \
    mapets-rl evaluate \$runs/mapets; \
    for r in maddpg m3ddpg mappo sac; do mapets-rl train \$r --env figure-eight \
        --run-dir \$runs/\$r total_frames=400 frames_per_batch=200 eval_interval=0 \
        device=cuda env_config.n_cavs=4; done; \
    mapets-rl train shapley_ac --env freeway --run-dir \$runs/shapley total_frames=200 \
        frames_per_batch=100 eval_interval=0 device=cuda; \
    mapets-rl train coma --env freeway --run-dir \$runs/coma total_frames=200 \
        frames_per_batch=100 eval_interval=0 device=cuda; echo all recipes trained on cuda"
