# Multi-stage build of the Spoofwatch server and the operator's CLI (`spoofwatch`, which links no
# server, learned baselines or plotting). The research CLI (`spoofwatch-lab`) is not shipped. Not
# built in this repository's CI: the development machines have no Docker engine (see
# docs/getting-started.md, "Containers").
#
# CPU: like every x86-64 build of this repository (.cargo/config.toml), the binaries target
# x86-64-v3 and need AVX2 (Intel Haswell / AMD Excavator or newer). For older CPUs build with
#   docker build --build-arg TARGET_CPU=x86-64 .
# (the results are bit for bit the same, the model step about 1.5x slower).
FROM rust:1.95-bookworm AS build
ARG TARGET_CPU=x86-64-v3
WORKDIR /src
COPY . .
# No debug line tables in the image (the repository's release profile keeps them for profiling).
RUN CARGO_PROFILE_RELEASE_DEBUG=false CARGO_PROFILE_RELEASE_STRIP=symbols \
    RUSTFLAGS="-C target-cpu=${TARGET_CPU}" \
    cargo build --release --locked --bin spoofwatch-server --bin spoofwatch

FROM debian:bookworm-slim
RUN useradd --system --uid 10001 --home-dir /var/lib/spoofwatch --create-home spoofwatch
COPY --from=build /src/target/release/spoofwatch-server /usr/local/bin/spoofwatch-server
COPY --from=build /src/target/release/spoofwatch /usr/local/bin/spoofwatch
USER spoofwatch
WORKDIR /var/lib/spoofwatch
ENV SPOOFWATCH_LISTEN=0.0.0.0:50051 \
    SPOOFWATCH_DATABASE=/var/lib/spoofwatch/spoofwatch.db
EXPOSE 50051
ENTRYPOINT ["/usr/local/bin/spoofwatch-server"]
