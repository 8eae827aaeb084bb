#!/usr/bin/env python3
"""Runs the README's grpcurl examples without grpcurl (not installable on the development machines).

It does what grpcurl does: server reflection for the descriptors, protobuf JSON (protojson) for the request
bodies, one call per example, and prints the JSON reply. Placeholders like `<id>` are filled from earlier
replies. Usage: start the server (with --data-dir ../shared/data/av-gps), then
    python3 scripts/grpcurl_check.py README.md 127.0.0.1:50051
Needs: pip install grpcio grpcio-reflection protobuf
"""
import json
import re
import shlex
import sys

import grpc
from google.protobuf import descriptor_pb2, descriptor_pool, json_format, message_factory
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase


def examples(readme):
    """(method, [json bodies]) for each grpcurl command in the README's grpcurl section."""
    text = open(readme, encoding="utf-8").read()
    section = text.split("### grpcurl", 1)[1].split("```sh", 1)[1].split("```", 1)[0]
    commands, current, heredoc = [], "", None
    for line in section.splitlines():
        if heredoc is not None:
            if line.strip() == "EOF":
                commands.append((current, heredoc))
                current, heredoc = "", None
            else:
                heredoc.append(line)
            continue
        if line.startswith("#") or not line.strip():
            continue
        current += " " + line.rstrip().rstrip("\\")
        # A command goes on after a trailing backslash or inside an open single-quoted body.
        if line.rstrip().endswith("\\") or current.count("'") % 2 == 1:
            continue
        if "<<'EOF'" in current:
            current = current.replace("<<'EOF'", "")
            heredoc = []
            continue
        commands.append((current, None))
        current = ""
    for command, stdin in commands:
        words = shlex.split(command)
        assert words[0] == "grpcurl", command
        body = words[words.index("-d") + 1] if "-d" in words else None
        method = words[-1] if words[-1] != "list" else "list"
        bodies = stdin if body == "@" else ([body] if body else ["{}"])
        yield method, bodies


def main(readme, target):
    channel = grpc.insecure_channel(target)
    database = ProtoReflectionDescriptorDatabase(channel)
    pool = descriptor_pool.DescriptorPool(database)
    filled = {}
    failures = 0
    for method, bodies in examples(readme):
        if method == "list":
            print("list ->", sorted(database.get_services()))
            continue
        service_name, method_name = method.rsplit("/", 1)
        service = pool.FindServiceByName(service_name)
        rpc = service.methods_by_name[method_name]
        request_class = message_factory.GetMessageClass(rpc.input_type)
        response_class = message_factory.GetMessageClass(rpc.output_type)
        requests = []
        for body in bodies:
            for key, value in filled.items():
                body = body.replace(key, value)
            requests.append(json_format.Parse(body, request_class()))
        path = f"/{service_name}/{method_name}"
        kind = (rpc.client_streaming, rpc.server_streaming)
        call = {
            (False, False): channel.unary_unary,
            (False, True): channel.unary_stream,
            (True, False): channel.stream_unary,
            (True, True): channel.stream_stream,
        }[kind](path, request_serializer=lambda m: m.SerializeToString(),
                response_deserializer=response_class.FromString)
        argument = iter(requests) if rpc.client_streaming else requests[0]
        try:
            reply = call(argument, timeout=120)
            replies = list(reply) if rpc.server_streaming else [reply]
            texts = [json_format.MessageToJson(r, indent=None, descriptor_pool=pool) for r in replies]
            print(f"OK   {method}: {len(replies)} message(s); {texts[-1][:160] if texts else ''}")
            for text in texts:
                for match in re.finditer(r'"name": "((?:datasets|operations)/[0-9a-f]+)"', text):
                    kind_name, ident = match.group(1).split("/")
                    placeholder = "<id from ImportDataset>" if kind_name == "datasets" else "<id>"
                    filled.setdefault(f"{kind_name}/{placeholder}", match.group(1))
                    if kind_name == "datasets":
                        filled.setdefault("datasets/<id>", match.group(1))
        except grpc.RpcError as error:
            failures += 1
            print(f"FAIL {method}: {error.code()} {error.details()}")
    print(f"{failures} failure(s)")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1], sys.argv[2]))
