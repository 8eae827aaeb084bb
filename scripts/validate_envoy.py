"""Validates the Envoy example offline against Envoy's own protobuf types (PyPI xds-protos, the
data-plane-api as generated Python): the YAML must parse into an envoy.config.bootstrap.v3.Bootstrap
with no unknown field and every typed_config resolvable, exactly as Envoy's loader reads it (the
protoc-gen-validate range rules are not checked). Then the choices the README documents are checked,
and the Kubernetes ConfigMap must carry the same file verbatim.

usage: validate_envoy.py deploy/envoy/envoy.yaml deploy/kubernetes/envoy.yaml
"""

import sys

import yaml
from google.protobuf import json_format

# The typed_config / extension types the example uses must be in the descriptor pool.
import envoy.extensions.filters.http.router.v3.router_pb2  # noqa: F401
import envoy.extensions.filters.network.http_connection_manager.v3.http_connection_manager_pb2 as hcm_pb2
import envoy.extensions.upstreams.http.v3.http_protocol_options_pb2  # noqa: F401
from envoy.config.bootstrap.v3.bootstrap_pb2 import Bootstrap
from envoy.config.cluster.v3.cluster_pb2 import Cluster

SERVER_STREAM_IDLE_S = 300


def fail(message):
    sys.exit(f"envoy: {message}")


def main(envoy_path, configmap_path):
    with open(envoy_path) as f:
        text = f.read()
    bootstrap = Bootstrap()
    try:
        json_format.ParseDict(yaml.safe_load(text), bootstrap)
    except json_format.ParseError as e:
        fail(f"{envoy_path} is not a valid Envoy bootstrap: {e}")

    (cluster,) = [c for c in bootstrap.static_resources.clusters if c.name == "spoofwatch_replicas"]
    if cluster.lb_policy != Cluster.RING_HASH:
        fail("the replicas' cluster must use lb_policy RING_HASH")
    if cluster.type != Cluster.STRICT_DNS:
        fail("the replicas' cluster must resolve every replica (STRICT_DNS)")
    checks = [h.grpc_health_check.service_name for h in cluster.health_checks if h.HasField("grpc_health_check")]
    if checks != ["spoofwatch.v1.DetectionService"]:
        fail(f"expected one gRPC health check of spoofwatch.v1.DetectionService, got {checks}")
    if not cluster.HasField("outlier_detection"):
        fail("the replicas' cluster needs outlier detection")

    (listener,) = bootstrap.static_resources.listeners
    hcm = hcm_pb2.HttpConnectionManager()
    listener.filter_chains[0].filters[0].typed_config.Unpack(hcm)
    if hcm.stream_idle_timeout.seconds <= SERVER_STREAM_IDLE_S:
        fail(f"stream_idle_timeout must exceed the server's --stream-idle-secs ({SERVER_STREAM_IDLE_S} s)")
    routes = [r for vh in hcm.route_config.virtual_hosts for r in vh.routes]
    for route in routes:
        headers = [p.header.header_name for p in route.route.hash_policy]
        if headers != ["x-vehicle-id"]:
            fail(f"every route must hash on the x-vehicle-id header, got {headers}")
        if route.route.timeout.ToSeconds() != 0:
            fail("routes must not put a deadline on (long-lived) streams: timeout 0s")

    with open(configmap_path) as f:
        documents = [d for d in yaml.safe_load_all(f) if d]
    (configmap,) = [d for d in documents if d["kind"] == "ConfigMap"]
    if configmap["data"]["envoy.yaml"] != text:
        fail(f"the ConfigMap in {configmap_path} does not carry {envoy_path} verbatim")
    print(f"{envoy_path}: a valid Envoy bootstrap (ring hash on x-vehicle-id, gRPC health checks); {configmap_path} carries it")


if __name__ == "__main__":
    if len(sys.argv) != 3:
        sys.exit(__doc__)
    main(sys.argv[1], sys.argv[2])
