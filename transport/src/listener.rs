//! The connections a server takes, bounded: at most [`MAX_CONNECTIONS`] open at once (the rest
//! wait in the kernel's backlog), each of which must start speaking within
//! [`HANDSHAKE_TIMEOUT`], and an accept that fails (out of file descriptors) retried after a
//! pause rather than at once. Without these, 300 sockets that never sent a byte held every
//! descriptor of a server under `ulimit -n 256`, and its accept loop spun at 96 % CPU refusing
//! everyone.

use std::io;
use std::pin::Pin;
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{OwnedSemaphorePermit, Semaphore, mpsc};
use tokio::time::Sleep;
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::server::{Connected, TcpConnectInfo};

/// Connections one server holds at once. An actor machine opens two or three, a flight stack
/// one; 128 leaves room for a large run while keeping a server far from a 256-descriptor limit.
pub const MAX_CONNECTIONS: usize = 128;
/// How long a new connection may stay silent before its first bytes (the HTTP/2 preface or a
/// TLS ClientHello), and how long a TLS handshake may take.
pub const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// Pause after a failed accept (EMFILE, ENFILE, ENOBUFS): the condition lasts until a
/// connection closes, so retrying at once only burns the CPU.
const ACCEPT_RETRY: Duration = Duration::from_millis(100);
/// Bytes of the HTTP/2 client preface: a client that sent them has started speaking.
const PREFACE_BYTES: usize = 24;

/// An accepted connection: the stream, with Nagle's algorithm off (tonic applies `tcp_nodelay`
/// only to listeners it binds; without it streamed parts wait out delayed ACKs of ~40 ms), its
/// place among the server's [`MAX_CONNECTIONS`], and the deadline for its first bytes.
pub struct Connection {
    stream: TcpStream,
    _place: OwnedSemaphorePermit,
    greeting_deadline: Option<Pin<Box<Sleep>>>,
    greeted: usize,
}

/// The connections accepted on `listener` (call inside a tokio runtime: a task accepts them).
pub fn incoming(listener: TcpListener) -> ReceiverStream<io::Result<Connection>> {
    let (tx, rx) = mpsc::channel(1);
    let places = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    tokio::spawn(async move {
        let mut failures = 0u64;
        loop {
            // The server dropping the stream (shutdown) ends the loop and closes the listener.
            let place = tokio::select! {
                place = places.clone().acquire_owned() => place,
                () = tx.closed() => return,
            };
            let Ok(place) = place else { return };
            let accepted = tokio::select! {
                accepted = listener.accept() => accepted,
                () = tx.closed() => return,
            };
            match accepted {
                Ok((stream, _)) => {
                    // A socket that refuses the option still works, only slower.
                    let _ = stream.set_nodelay(true);
                    let connection = Connection {
                        stream,
                        _place: place,
                        greeting_deadline: Some(Box::pin(tokio::time::sleep(HANDSHAKE_TIMEOUT))),
                        greeted: 0,
                    };
                    if tx.send(Ok(connection)).await.is_err() {
                        return;
                    }
                }
                Err(e) => {
                    failures += 1;
                    if failures.is_power_of_two() {
                        tracing::warn!("accepting a connection failed ({failures} times so far): {e}; retrying in {ACCEPT_RETRY:?}");
                    }
                    tokio::time::sleep(ACCEPT_RETRY).await;
                }
            }
        }
    });
    ReceiverStream::new(rx)
}

impl AsyncRead for Connection {
    fn poll_read(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &mut ReadBuf<'_>) -> Poll<io::Result<()>> {
        let this = self.get_mut();
        let before = buf.filled().len();
        let read = Pin::new(&mut this.stream).poll_read(cx, buf);
        let Some(deadline) = this.greeting_deadline.as_mut() else { return read };
        match read {
            Poll::Ready(Ok(())) => {
                this.greeted += buf.filled().len() - before;
                if this.greeted >= PREFACE_BYTES {
                    this.greeting_deadline = None;
                }
            }
            Poll::Pending if deadline.as_mut().poll(cx).is_ready() => {
                return Poll::Ready(Err(io::Error::new(
                    io::ErrorKind::TimedOut,
                    format!("no greeting within {HANDSHAKE_TIMEOUT:?}: connection closed"),
                )));
            }
            _ => {}
        }
        read
    }
}

impl AsyncWrite for Connection {
    fn poll_write(self: Pin<&mut Self>, cx: &mut Context<'_>, buf: &[u8]) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().stream).poll_write(cx, buf)
    }

    fn poll_write_vectored(self: Pin<&mut Self>, cx: &mut Context<'_>, bufs: &[io::IoSlice<'_>]) -> Poll<io::Result<usize>> {
        Pin::new(&mut self.get_mut().stream).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.stream.is_write_vectored()
    }

    fn poll_flush(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().stream).poll_flush(cx)
    }

    fn poll_shutdown(self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<io::Result<()>> {
        Pin::new(&mut self.get_mut().stream).poll_shutdown(cx)
    }
}

impl Connected for Connection {
    type ConnectInfo = TcpConnectInfo;

    fn connect_info(&self) -> TcpConnectInfo {
        self.stream.connect_info()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tokio::io::AsyncReadExt;
    use tokio_stream::StreamExt;

    #[tokio::test(start_paused = true)]
    async fn a_silent_connection_is_closed_and_one_that_speaks_is_kept() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let mut connections = incoming(listener);
        let _silent = TcpStream::connect(addr).await.unwrap();
        let mut silent = connections.next().await.unwrap().unwrap();
        let mut speaking_client = TcpStream::connect(addr).await.unwrap();
        let mut speaking = connections.next().await.unwrap().unwrap();
        tokio::io::AsyncWriteExt::write_all(&mut speaking_client, b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n").await.unwrap();
        let mut preface = [0u8; PREFACE_BYTES];
        speaking.read_exact(&mut preface).await.unwrap();
        // The clock is paused: reading waits out the deadline at once.
        let error = silent.read(&mut [0u8; 8]).await.unwrap_err();
        assert_eq!(error.kind(), io::ErrorKind::TimedOut, "{error}");
        let still_open = tokio::time::timeout(HANDSHAKE_TIMEOUT * 3, speaking.read(&mut [0u8; 8])).await;
        assert!(still_open.is_err(), "a connection that spoke has no deadline: {still_open:?}");
    }

    #[tokio::test]
    async fn connections_beyond_the_bound_wait_until_one_closes() {
        let listener = TcpListener::bind("127.0.0.1:0").await.unwrap();
        let addr = listener.local_addr().unwrap();
        let mut connections = incoming(listener);
        let mut clients = Vec::new();
        let mut accepted = Vec::new();
        for _ in 0..MAX_CONNECTIONS {
            clients.push(TcpStream::connect(addr).await.unwrap());
            accepted.push(connections.next().await.unwrap().unwrap());
        }
        // One more connects (the kernel's backlog takes it) but is not accepted…
        clients.push(TcpStream::connect(addr).await.unwrap());
        let waiting = tokio::time::timeout(Duration::from_millis(300), connections.next()).await;
        assert!(waiting.is_err(), "accepted beyond {MAX_CONNECTIONS}");
        // …until one of the others closes.
        drop(accepted.pop());
        let taken = tokio::time::timeout(Duration::from_secs(5), connections.next()).await;
        assert!(matches!(taken, Ok(Some(Ok(_)))), "the waiting connection was not accepted after a close");
    }
}
