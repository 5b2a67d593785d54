//! A small blocking client of `omnid serve` (used by `omnid watch`, `omnid ctl`, the tests
//! and the benchmark): connect and greet, send requests, wait for their replies, read the
//! state stream.

use crate::protocol::{Hello, State, MAX_MESSAGE, PROTOCOL_VERSION};
use crate::socket::Conn;
use serde_json::{json, Value};
use std::path::Path;
use thiserror::Error;

/// What went wrong talking to the daemon.
#[derive(Debug, Error)]
pub enum ClientError {
    /// No daemon answered at the socket.
    #[error("cannot connect to {path}: {source}")]
    Connect {
        /// The socket path.
        path: String,
        /// What the connect said.
        source: std::io::Error,
    },
    /// The socket failed after connecting.
    #[error("{0}")]
    Io(#[from] std::io::Error),
    /// The daemon refused the request; its reason.
    #[error("{0}")]
    Refused(String),
    /// The daemon closed the connection.
    #[error("the daemon closed the connection")]
    Closed,
    /// Nothing came within the wait, ms.
    #[error("no answer within {0} ms")]
    Timeout(i32),
    /// The daemon sent something that is not a protocol message.
    #[error("unreadable message from the daemon: {0}")]
    Protocol(String),
}

/// A message from the daemon. (A state is the larger variant; a client reads one message at
/// a time, so it is not boxed.)
#[allow(clippy::large_enum_variant)]
#[derive(Debug, Clone)]
pub enum Message {
    /// A state of the stream.
    State(State),
    /// Anything else (`reply`, `error`, `event`, `lost`, `bye`), as JSON.
    Other(Value),
}

/// A connection to `omnid serve`, greeted (docs/PROTOCOL.md): requests with their replies,
/// and the state stream.
pub struct Client {
    conn: Conn,
    hello: Hello,
    buf: Vec<u8>,
    next_id: u64,
    /// Messages read while waiting for a reply, handed out by `recv` first.
    backlog: std::collections::VecDeque<Message>,
}

impl Client {
    /// Connect to the daemon at `path` and say hello as `name`.
    pub fn connect(path: &Path, name: &str) -> Result<Client, ClientError> {
        let conn = Conn::connect(path).map_err(|source| ClientError::Connect {
            path: path.display().to_string(),
            source,
        })?;
        let mut c = Client {
            conn,
            hello: Hello {
                protocol: 0,
                server: String::new(),
                device: String::new(),
                arm: String::new(),
                aliases: Vec::new(),
                rate_hz: 0.0,
                access: String::new(),
                client: 0,
                stream_ttl_ms: 0.0,
                controllers: Vec::new(),
                modes: Vec::new(),
                model: String::new(),
                vendor: String::new(),
                serial: None,
                firmware: None,
            },
            buf: vec![0; MAX_MESSAGE + 1],
            next_id: 1,
            backlog: Default::default(),
        };
        // A refused peer finds the daemon's reason waiting and the connection closed: the
        // hello may fail, the reason is still there to read.
        let sent = c.send(&json!({ "op": "hello", "protocol": PROTOCOL_VERSION, "name": name }));
        loop {
            let message = match c.read(5000) {
                Ok(m) => m,
                // Nothing to read either: the send's error says more.
                Err(e) => return Err(sent.err().unwrap_or(e)),
            };
            match message {
                Message::Other(v) if v["type"] == "hello" => {
                    c.hello = serde_json::from_value(v)
                        .map_err(|e| ClientError::Protocol(e.to_string()))?;
                    return Ok(c);
                }
                Message::Other(v) if v["type"] == "error" => {
                    return Err(ClientError::Refused(
                        v["message"].as_str().unwrap_or("refused").to_string(),
                    ))
                }
                _ => sent.as_ref().map_err(|_| ClientError::Closed).map(|_| ())?,
            }
        }
    }

    /// The daemon's greeting.
    pub fn hello(&self) -> &Hello {
        &self.hello
    }

    /// Send one request as it is (no reply awaited).
    pub fn send(&self, msg: &Value) -> Result<(), ClientError> {
        let bytes = serde_json::to_vec(msg).map_err(|e| ClientError::Protocol(e.to_string()))?;
        self.conn.send(&bytes).map_err(|e| match e.kind() {
            std::io::ErrorKind::BrokenPipe | std::io::ErrorKind::ConnectionReset => {
                ClientError::Closed
            }
            _ => ClientError::Io(e),
        })
    }

    /// Send raw bytes (tests of malformed input).
    pub fn send_raw(&self, bytes: &[u8]) -> Result<(), ClientError> {
        Ok(self.conn.send(bytes)?)
    }

    fn read(&mut self, timeout_ms: i32) -> Result<Message, ClientError> {
        if !self.conn.wait_readable(timeout_ms)? {
            return Err(ClientError::Timeout(timeout_ms));
        }
        // A daemon that refuses a connection sends its reason and closes; if our hello was
        // still unread the kernel reports a reset first, and the reason is still queued.
        let n = match self.conn.recv(&mut self.buf) {
            Err(e) if e.kind() == std::io::ErrorKind::ConnectionReset => self
                .conn
                .recv(&mut self.buf)
                .map_err(|_| ClientError::Closed)?,
            r => r?,
        };
        if n == 0 {
            return Err(ClientError::Closed);
        }
        let bytes = &self.buf[..n.min(self.buf.len())];
        let v: Value =
            serde_json::from_slice(bytes).map_err(|e| ClientError::Protocol(e.to_string()))?;
        if v["type"] == "state" {
            return serde_json::from_value(v)
                .map(Message::State)
                .map_err(|e| ClientError::Protocol(e.to_string()));
        }
        Ok(Message::Other(v))
    }

    /// The next message, waiting at most `timeout_ms` (negative: forever).
    pub fn recv(&mut self, timeout_ms: i32) -> Result<Message, ClientError> {
        match self.backlog.pop_front() {
            Some(m) => Ok(m),
            None => self.read(timeout_ms),
        }
    }

    /// The next state sample, skipping other messages (kept for `recv`).
    pub fn next_state(&mut self, timeout_ms: i32) -> Result<State, ClientError> {
        if let Some(k) = self
            .backlog
            .iter()
            .position(|m| matches!(m, Message::State(_)))
        {
            if let Some(Message::State(s)) = self.backlog.remove(k) {
                return Ok(s);
            }
        }
        loop {
            match self.read(timeout_ms)? {
                Message::State(s) => return Ok(s),
                other => self.backlog.push_back(other),
            }
        }
    }

    /// Send `request` (an object with `op`) and wait for its reply; the daemon's refusal is
    /// `ClientError::Refused` with its reason. State samples and events that arrive
    /// meanwhile are kept for `recv` (samples only while streaming was asked for).
    pub fn request(&mut self, mut request: Value) -> Result<Value, ClientError> {
        let id = self.next_id;
        self.next_id += 1;
        request["id"] = json!(id);
        self.send(&request)?;
        loop {
            match self.read(10_000)? {
                Message::Other(v) if v["id"] == json!(id) => {
                    return if v["type"] == "error" {
                        Err(ClientError::Refused(
                            v["message"].as_str().unwrap_or("refused").to_string(),
                        ))
                    } else {
                        Ok(v)
                    };
                }
                // The daemon's answer to a message it could not read has no id.
                Message::Other(v) if v["type"] == "error" && v.get("id").is_none() => {
                    return Err(ClientError::Refused(
                        v["message"].as_str().unwrap_or("refused").to_string(),
                    ))
                }
                Message::Other(v) if v["type"] == "bye" => return Err(ClientError::Closed),
                other => {
                    if self.backlog.len() < 100_000 {
                        self.backlog.push_back(other);
                    }
                }
            }
        }
    }
}
