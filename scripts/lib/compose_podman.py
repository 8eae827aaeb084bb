#!/usr/bin/python3
"""Runs the shipped compose.yaml with podman, as `docker compose up --exit-code-from SERVICE` would.

Debian 12's podman-compose (1.0.3) starts services without waiting for `condition: service_healthy`, and
podman runs no health checks on its own without systemd; this runner does both, so that the smoke test
runs gated by the server's health check exactly as compose.yaml says. It understands the keys compose.yaml
uses and refuses any other, so that a change to compose.yaml that it would silently ignore fails instead.

The services share one pod (one network namespace): each service's name resolves to it through
--add-host, as Compose's network DNS does. `build: .` services run IMAGE (built beforehand by the caller
from the same Dockerfile). Prints what it runs; exits with the exit code of --exit-code-from's service, or
1 when a service failed its health check or the stopped services did not exit 0 within their
stop_grace_period.

Usage: compose_podman.py COMPOSE_FILE --project NAME --image IMAGE --exit-code-from SERVICE
       [--podman 'podman --runtime runc'] [--label KEY=VALUE]
"""

import argparse
import json
import re
import shlex
import subprocess
import sys
import time

import yaml

SERVICE_KEYS = {"build", "image", "volumes", "stop_grace_period", "healthcheck", "depends_on",
                "entrypoint", "command", "environment"}
HEALTH_KEYS = {"test", "interval", "timeout", "retries", "start_period"}


def seconds(text, what):
    """Compose durations as compose.yaml writes them: 20s, 2s, 1m, 1m30s, 500ms."""
    parts = re.fullmatch(r"(?:(\d+)m(?!s))?(?:(\d+)s)?(?:(\d+)ms)?", str(text))
    if not parts or not any(parts.groups()):
        sys.exit(f"compose: {what}: {text!r} is not a duration such as 20s")
    minutes, secs, millis = (int(g or 0) for g in parts.groups())
    return minutes * 60 + secs + millis / 1000


def run(podman, *args, check=True, capture=False):
    command = podman + list(args)
    print("+ " + shlex.join(command), flush=True)
    result = subprocess.run(command, text=True, capture_output=capture)
    if check and result.returncode != 0:
        if capture:
            sys.stderr.write(result.stdout + result.stderr)
        sys.exit(f"compose: {shlex.join(command)} failed with exit status {result.returncode}")
    return result


def start_order(services):
    order, seen = [], set()

    def visit(name, path):
        if name in path:
            sys.exit(f"compose: depends_on forms a circle through {name}")
        if name in seen:
            return
        for dep in services[name].get("depends_on", {}):
            if dep not in services:
                sys.exit(f"compose: {name} depends on {dep}, which is not a service")
            visit(dep, path | {name})
        seen.add(name)
        order.append(name)

    for name in services:
        visit(name, set())
    return order


def health_flags(check):
    unknown = set(check) - HEALTH_KEYS
    if unknown:
        sys.exit(f"compose: healthcheck keys this runner does not know: {sorted(unknown)}")
    test = check["test"]
    if not (isinstance(test, list) and test and test[0] in ("CMD", "CMD-SHELL")):
        sys.exit(f"compose: healthcheck test {test!r}: expected [\"CMD\", ...] or [\"CMD-SHELL\", ...]")
    # podman 4.3 takes no JSON array here: CMD's words as one line (no shell), CMD-SHELL's line.
    command = shlex.join(test[1:]) if test[0] == "CMD" else test[1]
    return ["--health-cmd", command,
            "--health-interval", f"{seconds(check.get('interval', '30s'), 'interval')}s",
            "--health-timeout", f"{seconds(check.get('timeout', '30s'), 'timeout')}s",
            "--health-retries", str(check.get("retries", 3))]


def wait_healthy(podman, container, check):
    """Runs the health check every interval until it passes, at most `retries` failures (podman
    without systemd schedules no checks itself)."""
    interval = seconds(check.get("interval", "30s"), "interval")
    retries = int(check.get("retries", 3))
    for attempt in range(1, retries + 1):
        result = run(podman, "healthcheck", "run", container, check=False, capture=True)
        if result.returncode == 0:
            print(f"compose: {container} healthy (check {attempt} of at most {retries})", flush=True)
            return True
        state = run(podman, "inspect", "--format", "{{.State.Status}}", container,
                    check=False, capture=True).stdout.strip()
        if state != "running":
            print(f"compose: {container} is {state}, not running", file=sys.stderr)
            return False
        time.sleep(interval)
    print(f"compose: {container} still unhealthy after {retries} checks", file=sys.stderr)
    return False


def container_args(project, name, service, image, volumes):
    unknown = set(service) - SERVICE_KEYS
    if unknown:
        sys.exit(f"compose: service {name}: keys this runner does not know: {sorted(unknown)}")
    if service.get("build", ".") != "." and "image" not in service:
        sys.exit(f"compose: service {name}: only `build: .` (the repository's Dockerfile) is known")
    args = ["--name", f"{project}-{name}", "--pod", project, "--detach"]
    for mount in service.get("volumes", []):
        source, _, target = mount.partition(":")
        if source not in volumes:
            sys.exit(f"compose: service {name}: volume {source} is not declared under volumes")
        args += ["--volume", f"{project}_{source}:{target}"]
    environment = service.get("environment", {})
    if isinstance(environment, list):
        environment = dict(item.split("=", 1) for item in environment)
    for key, value in environment.items():
        args += ["--env", f"{key}={value}"]
    if "healthcheck" in service:
        args += health_flags(service["healthcheck"])
    entrypoint = service.get("entrypoint")
    if entrypoint is not None:
        args += ["--entrypoint", json.dumps(entrypoint if isinstance(entrypoint, list) else shlex.split(entrypoint))]
    args.append(service.get("image", image))
    command = service.get("command")
    if command is not None:
        args += command if isinstance(command, list) else shlex.split(command)
    return args


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("compose_file")
    parser.add_argument("--project", required=True)
    parser.add_argument("--image", required=True)
    parser.add_argument("--exit-code-from", required=True)
    parser.add_argument("--podman", default="podman")
    parser.add_argument("--label", help="KEY=VALUE put on the pod, volumes and containers")
    args = parser.parse_args()
    podman = shlex.split(args.podman)
    spec = yaml.safe_load(open(args.compose_file))
    unknown = set(spec) - {"services", "volumes"}
    if unknown:
        sys.exit(f"compose: top-level keys this runner does not know: {sorted(unknown)}")
    services, volumes = spec["services"], spec.get("volumes") or {}
    if args.exit_code_from not in services:
        sys.exit(f"compose: no service {args.exit_code_from}")

    hosts = [f"--add-host={name}:127.0.0.1" for name in services]
    labels = ["--label", args.label] if args.label else []
    run(podman, "pod", "create", "--name", args.project, *labels, *hosts)
    for volume in volumes:
        run(podman, "volume", "create", *labels, f"{args.project}_{volume}")
    for name in start_order(services):
        for dep, condition in (services[name].get("depends_on") or {}).items():
            wanted = (condition or {}).get("condition", "service_started")
            if wanted == "service_healthy":
                if not wait_healthy(podman, f"{args.project}-{dep}", services[dep]["healthcheck"]):
                    run(podman, "logs", f"{args.project}-{dep}", check=False)
                    return 1
            elif wanted != "service_started":
                sys.exit(f"compose: {name}: depends_on condition {wanted} is not known")
        run(podman, "run", *labels, *container_args(args.project, name, services[name], args.image, volumes))

    target = f"{args.project}-{args.exit_code_from}"
    code = int(run(podman, "wait", target, capture=True).stdout.strip())
    run(podman, "logs", target, check=False)
    print(f"compose: {args.exit_code_from} exited {code}", flush=True)
    failed = code != 0
    for name in reversed(start_order(services)):
        if name == args.exit_code_from:
            continue
        grace = seconds(services[name].get("stop_grace_period", "10s"), "stop_grace_period")
        started = time.monotonic()
        run(podman, "stop", "--time", str(int(grace)), f"{args.project}-{name}")
        took = time.monotonic() - started
        status = int(run(podman, "inspect", "--format", "{{.State.ExitCode}}", f"{args.project}-{name}",
                         capture=True).stdout.strip())
        print(f"compose: {name} stopped in {took:.1f} s (grace {grace:g} s), exit status {status}", flush=True)
        if status != 0:
            failed = True
    return code if code != 0 else (1 if failed else 0)


if __name__ == "__main__":
    sys.exit(main())
