#!/usr/bin/env bash
# Validates the deployment examples under deploy/ offline (run by .ci/run):
# - Kubernetes manifests: kubernetes-validate (PyPI; Kubernetes' own OpenAPI schemas), strict
#   (unknown fields fail);
# - Envoy: scripts/validate_envoy.py parses deploy/envoy/envoy.yaml into Envoy's own protobuf types
#   (PyPI xds-protos) and checks the documented choices and the ConfigMap copy;
# - HAProxy: `haproxy -c` on deploy/haproxy/spoofwatch.cfg when haproxy is installed (its behaviour
#   is tested for real in tests/tests/haproxy_routes_vehicles.rs);
# - Prometheus: `promtool check rules` and the rules' unit tests (`promtool test rules`) when promtool
#   is installed (.ci/run installs it); the Grafana dashboard must parse as JSON, with unique panel ids,
#   a query with an expression in every panel and no panels overlapping (scripts/validate_dashboard.py).
#   That both name only exported metrics is tested against a real scrape in
#   tests/tests/dashboard_metrics.rs.
# The Python tools go into a venv under target/ci-tools (SPOOFWATCH_CI_TOOLS to put it elsewhere).
set -euo pipefail
cd "$(dirname "$0")/.."
tools="${SPOOFWATCH_CI_TOOLS:-target/ci-tools}"

if ! "$tools/bin/python" -c 'import kubernetes_validate, yaml, envoy.config.bootstrap.v3.bootstrap_pb2' 2>/dev/null; then
  [ -x "$tools/bin/pip" ] || python3 -m venv "$tools"
  "$tools/bin/pip" install -q xds-protos==1.85.0 kubernetes-validate==1.37.0
fi

echo "== Kubernetes manifests (kubernetes-validate --strict, Kubernetes 1.37 schemas)"
"$tools/bin/kubernetes-validate" --strict --kubernetes-version 1.37.0 deploy/kubernetes/*.yaml

echo "== Envoy (Envoy's protobuf types from xds-protos)"
"$tools/bin/python" scripts/validate_envoy.py deploy/envoy/envoy.yaml deploy/kubernetes/envoy.yaml

echo "== HAProxy (haproxy -c)"
haproxy="${SPOOFWATCH_HAPROXY:-$(command -v haproxy || true)}"
if [ -n "$haproxy" ]; then
  SPOOFWATCH_LB_LISTEN=127.0.0.1:50050 SPOOFWATCH_REPLICA_1=127.0.0.1:50051 \
    SPOOFWATCH_REPLICA_2=127.0.0.1:50052 "$haproxy" -c -q -f deploy/haproxy/spoofwatch.cfg
  echo "deploy/haproxy/spoofwatch.cfg: valid"
else
  echo "no haproxy installed: skipped (.ci/run installs it)"
fi

echo "== Prometheus rules (promtool check rules, promtool test rules)"
if command -v promtool >/dev/null; then
  promtool check rules deploy/prometheus/*.rules.yml
  promtool test rules deploy/prometheus/*.test.yml
else
  echo "no promtool installed: skipped (.ci/run installs it)"
fi

echo "== Grafana dashboard (scripts/validate_dashboard.py)"
python3 scripts/validate_dashboard.py deploy/grafana/*.json
