//! omnid's client library: what a program needs to read an Omni's state from `omnid serve`
//! and command it, and nothing of the daemon (docs/PROTOCOL.md). libHD is built on it; the
//! daemon uses the same types, so both sides cannot drift apart.
//!
//! - [`protocol`]: the protocol version, the largest message, the greeting, an arm's state;
//! - [`socket`]: the SOCK_SEQPACKET connection and the peer's credentials;
//! - [`client`]: a blocking client (greet, request and reply, the state stream);
//! - [`find`]: where the daemon's sockets are, an arm's socket by name or alias;
//! - [`kinematics`]: the Omni's forward kinematics and Jacobian (OpenHaptics convention);
//! - [`realtime`]: SCHED_FIFO for a client's own 1 kHz thread.

#![warn(missing_docs)]

pub mod client;
pub mod find;
pub mod kinematics;
pub mod protocol;
pub mod realtime;
pub mod socket;

pub use client::{Client, ClientError, Message};
pub use find::{find_arm_socket, find_socket};
