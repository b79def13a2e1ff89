#!/usr/bin/env bash
# A single-node SLURM on this machine, to try the cluster profile for real (CI runs it too).
# Needs Debian's (or Ubuntu's) slurmctld, slurmd and munge packages and root:
#   apt-get install slurmctld slurmd munge
#
#   workflow/profiles/slurm/single-node.sh up DIR [--gpu] [--cpus N]   start munged, slurmctld, slurmd
#   . DIR/env                                              SLURM_CONF for sbatch, squeue, scontrol
#   workflow/profiles/slurm/single-node.sh down DIR          stop the daemons it started
#
# One node sized from nproc and free (80 % of the memory), partitions `cpu` (default) and `gpu`, no
# accounting (so the profile's placeholder account is accepted), MinJobAge one hour (finished jobs
# stay in squeue, which the profile's status checks read). --gpu declares one GRES gpu on the node
# (mapped to no device: jobs still compute on the CPU) so GPU rules can land on `gpu`. --cpus N
# declares N CPUs instead of nproc (more jobs at once where they mostly wait, as in CI's tiny runs).
# Everything lives in DIR: the configuration, the daemons' state, logs and process ids, and
# DIR/partitions.yaml, the node's limits for config resources.partition_config. While it runs,
# /etc/slurm/slurm.conf links to DIR/slurm.conf (job steps read the default path); the script
# refuses to start where a SLURM configuration already exists.
set -euo pipefail

usage() { echo "usage: $0 up DIR [--gpu] [--cpus N] | down DIR" >&2; exit 2; }
[ $# -ge 2 ] || usage
action=$1
dir=$(realpath -m "$2")

# The jobs' own srun calls drop SLURM_CONF (the executor plugin cleans SLURM_* variables for its
# job steps), so they read the default path: the script links its configuration there while the
# cluster runs, and only where no other SLURM configuration is.
DEFAULT_CONF=/etc/slurm/slurm.conf

stop() {
  local pidfile pid
  for pidfile in "$dir/slurmd.pid" "$dir/slurmctld.pid" "$dir/munged.pid"; do
    [ -s "$pidfile" ] || continue
    pid=$(cat "$pidfile")
    kill "$pid" 2>/dev/null || true
    for _ in $(seq 50); do kill -0 "$pid" 2>/dev/null || break; sleep 0.1; done
    kill -9 "$pid" 2>/dev/null || true
    rm -f "$pidfile"
  done
  if [ "$(readlink "$DEFAULT_CONF" 2>/dev/null)" = "$dir/slurm.conf" ]; then rm -f "$DEFAULT_CONF"; fi
}

case $action in
down)
  stop
  exit 0
  ;;
up) ;;
*) usage ;;
esac

gpu=0
cpus=$(nproc)
shift 2
while [ $# -gt 0 ]; do
  case $1 in
  --gpu) gpu=1; shift ;;
  --cpus) [ $# -ge 2 ] || usage; cpus=$2; shift 2 ;;
  *) usage ;;
  esac
done
overrides=""
[ "$cpus" != "$(nproc)" ] && overrides="SlurmdParameters=config_overrides"
for tool in munged slurmctld slurmd sbatch squeue scontrol; do
  command -v "$tool" >/dev/null || PATH=$PATH:/usr/sbin:/sbin
  command -v "$tool" >/dev/null || { echo "$0: $tool not found (apt-get install slurmctld slurmd munge)" >&2; exit 1; }
done
[ "$(id -u)" = 0 ] || { echo "$0: slurmd must run as root to start jobs" >&2; exit 1; }

if [ -e "$DEFAULT_CONF" ] || [ -L "$DEFAULT_CONF" ]; then
  echo "$0: $DEFAULT_CONF exists: this machine has a SLURM configuration; the script starts a cluster only where none is" >&2
  exit 1
fi
mkdir -p "$dir/state" "$dir/spool" "$dir/munge"
chmod 700 "$dir/munge"
host=$(hostname -s)
mem_mb=$(( $(free -m | awk '/^Mem:/ {print $2}') * 8 / 10 ))
# Free ports for this cluster's daemons (another SLURM may use 6817/6818).
read -r ctld_port node_port < <(python3 -c '
import socket
socks = [socket.socket() for _ in range(2)]
for s in socks: s.bind(("127.0.0.1", 0))
print(*[s.getsockname()[1] for s in socks])')

key=/etc/munge/munge.key
if [ ! -s "$key" ]; then
  key=$dir/munge/munge.key
  head -c 1024 /dev/urandom > "$key"
  chmod 400 "$key"
fi
munged --force --socket="$dir/munge/munge.socket" --pid-file="$dir/munged.pid" --key-file="$key" \
  --log-file="$dir/munged.log" --seed-file="$dir/munge/seed"

gres=""
if [ $gpu = 1 ]; then
  gres="Gres=gpu:1"
  echo "NodeName=$host Name=gpu Count=1 File=/dev/null" > "$dir/gres.conf"
fi
cat > "$dir/slurm.conf" <<EOF
ClusterName=omnilidar
SlurmctldHost=$host(127.0.0.1)
SlurmctldPort=$ctld_port
SlurmdPort=$node_port
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket=$dir/munge/munge.socket
SlurmUser=root
SlurmdUser=root
StateSaveLocation=$dir/state
SlurmdSpoolDir=$dir/spool
SlurmctldPidFile=$dir/slurmctld.pid
SlurmdPidFile=$dir/slurmd.pid
SlurmctldLogFile=$dir/slurmctld.log
SlurmdLogFile=$dir/slurmd.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
MpiDefault=none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core_Memory
SchedulerType=sched/backfill
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
ReturnToService=2
MinJobAge=3600
$( [ $gpu = 1 ] && echo "GresTypes=gpu" )
$overrides
NodeName=$host NodeAddr=127.0.0.1 CPUs=$cpus RealMemory=$mem_mb $gres State=UNKNOWN
PartitionName=cpu Nodes=$host Default=YES MaxTime=INFINITE State=UP
PartitionName=gpu Nodes=$host MaxTime=INFINITE State=UP
EOF

cat > "$dir/partitions.yaml" <<EOF
# The single node's limits (written by $0).
partitions:
  cpu: {max_mem_mb: $mem_mb, max_cpus_per_task: $cpus, max_gpu: 0}
  gpu: {max_mem_mb: $mem_mb, max_cpus_per_task: $cpus, max_gpu: $gpu}
EOF
echo "export SLURM_CONF=$dir/slurm.conf" > "$dir/env"
export SLURM_CONF=$dir/slurm.conf
mkdir -p "$(dirname "$DEFAULT_CONF")"
ln -s "$dir/slurm.conf" "$DEFAULT_CONF"

slurmctld -f "$dir/slurm.conf"
slurmd -f "$dir/slurm.conf"
for _ in $(seq 150); do
  state=$(sinfo -h -N -o %t 2>/dev/null | head -1 || true)
  case $state in idle*|mix*|alloc*) echo "single-node SLURM up in $dir: node $host, $cpus CPUs, $mem_mb MB, $gpu GPU"; exit 0 ;; esac
  sleep 0.2
done
echo "$0: the node did not come up (state '${state:-none}'); see $dir/slurmctld.log and $dir/slurmd.log" >&2
stop
exit 1
