# Sourced by scripts/scale.sh and scripts/bench-store.sh: a SeaweedFS object store on
# loopback, as the tests start one (tests/src/scale.rs).
#
#   free_ports N              prints N free loopback ports p with p + 10000 free too
#                             (weed puts each of its servers' gRPC port there)
#   start_store WEED DIR LOG  exports the AWS_* variables its clients read, starts
#                             `weed mini` (bucket `tiles`, data in DIR, output to LOG) in the
#                             background, its pid in STORE_PID, and waits for its S3 endpoint

free_ports() {
  python3 - "$1" <<'PY'
import socket, sys
ports = []
while len(ports) < int(sys.argv[1]):
    s = socket.socket(); s.bind(("127.0.0.1", 0)); p = s.getsockname()[1]
    ok = p < 55000 and p not in ports
    if ok:
        try:
            t = socket.socket(); t.bind(("127.0.0.1", p + 10000)); t.close()
        except OSError:
            ok = False
    s.close()
    if ok:
        ports.append(p)
print(*ports)
PY
}

start_store() {
  local weed=$1 dir=$2 log=$3 master volume filer s3 admin
  read -r master volume filer s3 admin < <(free_ports 5)
  export AWS_ACCESS_KEY_ID=terrain AWS_SECRET_ACCESS_KEY=terrain-local-secret AWS_REGION=us-east-1
  export AWS_ENDPOINT="http://127.0.0.1:$s3" AWS_ALLOW_HTTP=true
  mkdir -p "$dir"
  "$weed" mini -dir="$dir" -ip=127.0.0.1 -ip.bind=127.0.0.1 -master.port="$master" \
    -volume.port="$volume" -filer.port="$filer" -s3.port="$s3" -admin.port="$admin" -admin.ui=false \
    -webdav=false -s3.port.iceberg=0 -s3.port.lance=0 -master.telemetry=false -bucket=tiles \
    >"$log" 2>&1 &
  STORE_PID=$!
  for _ in $(seq 300); do curl -s -o /dev/null "$AWS_ENDPOINT/" && return 0; sleep 0.2; done
  echo "the object store never answered on $AWS_ENDPOINT; its log: $log" >&2
  return 1
}
