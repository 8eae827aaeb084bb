//! Replies written together: a connection's writes are held until the tasks already waiting to
//! run have run, then leave in one write.
//!
//! Without it a gateway's connection costs a write, and a TCP segment, per reply: the task that
//! answers a stream wakes the connection's task, which the scheduler runs next and which flushes
//! at once, so N vehicles whose messages arrived in one read get N writes back. Here the first
//! flush after new data yields once instead (the task wakes itself, and so goes behind the tasks
//! already queued, such as the other streams' answers); the next flush writes everything held.
//! A reply waits for those tasks only, microseconds, and the kernel's per-write cost, most of the
//! server's when messages are small, is paid once per connection and round of work.
//!
//! It owns only the buffering between the HTTP/2 connection and its socket; it must not look at
//! what it carries.

use std::io;
use std::pin::Pin;
use std::task::{Context, Poll, ready};

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tonic::transport::server::{Connected, TcpConnectInfo};

/// Most bytes held before a write must wait for the socket (hyper's HTTP/2 writes frames in
/// chunks of about this size).
const HELD_LIMIT: usize = 64 * 1024;

/// A connection whose writes are held until a flush that comes after one yield.
#[derive(Debug)]
pub struct Coalescing<S> {
    inner: S,
    held: Vec<u8>,
    /// Bytes of `held` already written.
    written: usize,
    /// The flush has yielded once for what is held.
    yielded: bool,
}

impl<S> Coalescing<S> {
    pub fn new(inner: S) -> Self {
        Self {
            inner,
            held: Vec::with_capacity(4096),
            written: 0,
            yielded: false,
        }
    }
}

impl<S: AsyncWrite + Unpin> Coalescing<S> {
    /// Writes everything held to the socket.
    fn poll_write_held(&mut self, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        while self.written < self.held.len() {
            let n = ready!(Pin::new(&mut self.inner).poll_write(cx, &self.held[self.written..]))?;
            if n == 0 {
                return Poll::Ready(Err(io::ErrorKind::WriteZero.into()));
            }
            self.written += n;
        }
        self.held.clear();
        self.written = 0;
        Poll::Ready(Ok(()))
    }
}

impl<S: AsyncRead + Unpin> AsyncRead for Coalescing<S> {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<io::Result<()>> {
        Pin::new(&mut self.inner).poll_read(cx, buf)
    }
}

impl<S: AsyncWrite + Unpin> AsyncWrite for Coalescing<S> {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<io::Result<usize>> {
        if self.held.len() >= HELD_LIMIT {
            ready!(self.poll_write_held(cx))?;
        }
        self.held.extend_from_slice(buf);
        Poll::Ready(Ok(buf.len()))
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[io::IoSlice<'_>],
    ) -> Poll<io::Result<usize>> {
        if self.held.len() >= HELD_LIMIT {
            ready!(self.poll_write_held(cx))?;
        }
        let mut n = 0;
        for buf in bufs {
            self.held.extend_from_slice(buf);
            n += buf.len();
        }
        Poll::Ready(Ok(n))
    }

    fn is_write_vectored(&self) -> bool {
        true
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        if self.written < self.held.len() && !self.yielded {
            // Behind the tasks already queued: what they write leaves with this.
            self.yielded = true;
            cx.waker().wake_by_ref();
            return Poll::Pending;
        }
        ready!(self.poll_write_held(cx))?;
        self.yielded = false;
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        ready!(self.poll_write_held(cx))?;
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

impl<S: Connected<ConnectInfo = TcpConnectInfo>> Connected for Coalescing<S> {
    type ConnectInfo = TcpConnectInfo;

    fn connect_info(&self) -> TcpConnectInfo {
        self.inner.connect_info()
    }
}

#[cfg(test)]
mod tests {
    use std::task::Waker;

    use tokio::io::{AsyncReadExt, AsyncWriteExt, duplex};

    use super::*;

    #[test]
    fn a_flush_yields_once_then_writes_everything_held_in_one_write() {
        let (near, mut far) = duplex(1 << 20);
        let mut writer = Coalescing::new(near);
        let mut cx = Context::from_waker(Waker::noop());
        let mut pinned = Pin::new(&mut writer);
        assert!(matches!(
            pinned.as_mut().poll_write(&mut cx, b"one "),
            Poll::Ready(Ok(4))
        ));
        assert!(
            pinned.as_mut().poll_flush(&mut cx).is_pending(),
            "the first flush yields"
        );
        // What another task writes meanwhile leaves with it.
        assert!(matches!(
            pinned.as_mut().poll_write(&mut cx, b"two"),
            Poll::Ready(Ok(3))
        ));
        assert!(matches!(
            pinned.as_mut().poll_flush(&mut cx),
            Poll::Ready(Ok(()))
        ));
        assert!(
            matches!(pinned.as_mut().poll_flush(&mut cx), Poll::Ready(Ok(()))),
            "nothing held"
        );
        let mut received = [0u8; 7];
        let mut read = ReadBuf::new(&mut received);
        assert!(matches!(
            Pin::new(&mut far).poll_read(&mut cx, &mut read),
            Poll::Ready(Ok(()))
        ));
        assert_eq!(read.filled(), b"one two");
    }

    #[tokio::test]
    async fn everything_written_arrives_in_order_also_beyond_the_limit_and_at_shutdown() {
        // A small pipe: the writer must wait for the reader, and hold at most about the limit.
        let (near, mut far) = duplex(8 * 1024);
        let reader = tokio::spawn(async move {
            let mut all = Vec::new();
            far.read_to_end(&mut all).await.unwrap();
            all
        });
        let mut writer = Coalescing::new(near);
        let mut sent = Vec::new();
        for i in 0..2_000u32 {
            let chunk = format!("message {i};");
            writer.write_all(chunk.as_bytes()).await.unwrap();
            sent.extend_from_slice(chunk.as_bytes());
            assert!(writer.held.len() <= HELD_LIMIT + chunk.len());
            if i % 300 == 0 {
                writer.flush().await.unwrap();
            }
        }
        writer.shutdown().await.unwrap();
        drop(writer);
        assert_eq!(reader.await.unwrap(), sent);
    }
}
