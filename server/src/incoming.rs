//! Accepted TCP connections, handed to the gRPC server only once the client has sent the 24-byte
//! HTTP/2 connection preface (or, with TLS, the first 24 bytes of its ClientHello) within a
//! deadline. Without it a client could hold any number of connections open by never speaking: hyper
//! waits for the preface forever. Connections are vetted concurrently, so a slow client delays
//! nobody. With TLS, tonic then runs the handshake on the vetted connection, bounded by the same
//! timeout (`tls::server_tls`), so a client that stalls mid-handshake is closed too. Each is
//! handed over with its writes coalesced (`crate::coalesce`).

use std::time::Duration;

use tokio::net::{TcpListener, TcpStream};
use tokio::sync::mpsc;
use tokio_stream::wrappers::ReceiverStream;

use crate::coalesce::Coalescing;

/// Bytes of the HTTP/2 client connection preface (`PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n`).
const PREFACE_BYTES: usize = 24;
/// Connections vetted and waiting for the server to take them.
const QUEUE: usize = 1024;
/// Pause between two looks at a connection that has sent part of its preface.
const PEEK_PAUSE: Duration = Duration::from_millis(5);

/// The connections of `listener` whose clients send their first [`PREFACE_BYTES`] bytes within
/// `deadline`; the others are closed. The stream ends when the server stops reading it.
pub fn vetted(
    listener: TcpListener,
    deadline: Duration,
) -> ReceiverStream<std::io::Result<Coalescing<TcpStream>>> {
    let (tx, rx) = mpsc::channel(QUEUE);
    tokio::spawn(async move {
        loop {
            // The listener closes as soon as the server stops taking connections.
            let accepted = tokio::select! {
                _ = tx.closed() => break,
                accepted = listener.accept() => accepted,
            };
            let (stream, peer) = match accepted {
                Ok(accepted) => accepted,
                Err(error) => {
                    // e.g. out of file descriptors: wait rather than spin.
                    tracing::warn!(%error, "accepting a connection failed");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            };
            let tx = tx.clone();
            tokio::spawn(async move {
                match tokio::time::timeout(deadline, preface_sent(&stream)).await {
                    Ok(Ok(())) => {
                        let _ = stream.set_nodelay(true);
                        let _ = tx.send(Ok(Coalescing::new(stream))).await;
                    }
                    Ok(Err(error)) => {
                        tracing::debug!(%peer, %error, "connection failed before its preface")
                    }
                    Err(_) => tracing::info!(
                        %peer,
                        deadline_s = deadline.as_secs_f64(),
                        "closed a connection that sent no HTTP/2 preface in time"
                    ),
                }
            });
        }
    });
    ReceiverStream::new(rx)
}

/// Waits until the client has sent [`PREFACE_BYTES`] bytes (left unread for the server), or
/// fails when it closes the connection first.
async fn preface_sent(stream: &TcpStream) -> std::io::Result<()> {
    let mut buffer = [0u8; PREFACE_BYTES];
    loop {
        match stream.peek(&mut buffer).await? {
            0 => {
                return Err(std::io::Error::new(
                    std::io::ErrorKind::UnexpectedEof,
                    "closed by the client",
                ));
            }
            n if n >= PREFACE_BYTES => return Ok(()),
            // Part of it: `peek` would return at once again, so look again shortly.
            _ => tokio::time::sleep(PEEK_PAUSE).await,
        }
    }
}

#[cfg(test)]
mod tests {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    use tokio_stream::StreamExt;

    use super::*;

    #[tokio::test]
    async fn a_silent_connection_is_closed_and_a_speaking_one_is_handed_over() {
        let listener = TcpListener::bind("127.0.0.1:0").await.expect("bound");
        let addr = listener.local_addr().expect("address");
        let mut accepted = vetted(listener, Duration::from_millis(300));

        let mut silent = TcpStream::connect(addr).await.expect("connected");
        let mut partial = TcpStream::connect(addr).await.expect("connected");
        partial.write_all(b"PRI * HTTP/2.0").await.expect("sent");
        let mut speaking = TcpStream::connect(addr).await.expect("connected");
        speaking
            .write_all(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n")
            .await
            .expect("sent");

        let mut handed = tokio::time::timeout(Duration::from_secs(5), accepted.next())
            .await
            .expect("in time")
            .expect("a connection")
            .expect("no error");
        // The preface is still there for the server to read.
        let mut preface = [0u8; PREFACE_BYTES];
        handed.read_exact(&mut preface).await.expect("readable");
        assert_eq!(&preface, b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n");

        // The silent and the partial client are closed after the deadline (EOF or reset).
        for client in [&mut silent, &mut partial] {
            let mut byte = [0u8; 1];
            let read = tokio::time::timeout(Duration::from_secs(5), client.read(&mut byte))
                .await
                .expect("closed in time");
            assert!(matches!(read, Ok(0) | Err(_)), "{read:?}");
        }
    }
}
