# Multi-stage build of the Spoofwatch server and CLI. Not built in this repository's CI: the
# development machines have no Docker engine (see README, "Containers").
FROM rust:1.95-bookworm AS build
WORKDIR /src
COPY . .
RUN cargo build --release --locked --bin spoofwatch-server --bin spoofwatch

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
