# The Spoofwatch server and the operator's CLI (`spoofwatch`, which links no server, learned baselines
# or plotting). The research CLI (`spoofwatch-lab`) is not shipped.
#
# Two images of one runtime stage, which differ only in where the binaries come from:
#   docker build .                  the binaries compiled in the `build` stage (the default target)
#   docker build --target host .    the binaries already built on the host with
#                                   `cargo build --profile image --locked --bin spoofwatch-server --bin spoofwatch`
#                                   (target/image/; the only files .dockerignore lets in from target/)
# Both compile with the `image` profile of Cargo.toml. CI builds the image the second way, from a local
# Debian base, and runs it in containers (scripts/container-test.sh; docs/containers.md).
#
# The base images are parameters too, so that the build needs no registry when they exist locally:
#   --build-arg BASE_IMAGE=localhost/debian-bookworm   (any Debian 12 root file system)
#   --build-arg BUILD_IMAGE=...                        (a Rust toolchain on Debian 12, same glibc)
#
# CPU: like every x86-64 build of this repository (.cargo/config.toml), the binaries target
# x86-64-v3 and need AVX2 (Intel Haswell / AMD Excavator or newer). For older CPUs build with
#   docker build --build-arg TARGET_CPU=x86-64 .
# (the results are bit for bit the same, the model step about 1.5x slower).
ARG BUILD_IMAGE=docker.io/library/rust:1.95-bookworm
ARG BASE_IMAGE=docker.io/library/debian:bookworm-slim

FROM ${BUILD_IMAGE} AS build
ARG TARGET_CPU=x86-64-v3
WORKDIR /src
COPY . .
RUN RUSTFLAGS="-C target-cpu=${TARGET_CPU}" \
    cargo build --profile image --locked --bin spoofwatch-server --bin spoofwatch \
 && mkdir /binaries && cp target/image/spoofwatch-server target/image/spoofwatch /binaries/

# Everything but the binaries, shared by the two images below.
FROM ${BASE_IMAGE} AS runtime
# The data directory (mount a volume here) is the user's home, without shell dotfiles.
RUN useradd --system --uid 10001 --home-dir /var/lib/spoofwatch --no-create-home spoofwatch \
 && mkdir /var/lib/spoofwatch && chown spoofwatch:spoofwatch /var/lib/spoofwatch
# The bundled models as files too (the server has the default compiled in): an operator imports the
# paper-schema model with `spoofwatch models import --file /usr/share/spoofwatch/models/paper.json`.
COPY models/default.json models/paper.json /usr/share/spoofwatch/models/
USER spoofwatch
WORKDIR /var/lib/spoofwatch
ENV SPOOFWATCH_LISTEN=0.0.0.0:50051 \
    SPOOFWATCH_DATABASE=/var/lib/spoofwatch/spoofwatch.db
EXPOSE 50051
ENTRYPOINT ["/usr/local/bin/spoofwatch-server"]

# `--target host`: the binaries built on the host.
FROM runtime AS host
COPY target/image/spoofwatch-server target/image/spoofwatch /usr/local/bin/

# The default: the binaries of the build stage.
FROM runtime AS image
COPY --from=build /binaries/spoofwatch-server /binaries/spoofwatch /usr/local/bin/
