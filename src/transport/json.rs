//! The JSON side every two-way transport shares (docs/PROTOCOL.md): a message decoded into a
//! request and then into the station's op, the greeting, a greeted session's request served
//! and answered, and the shape of replies, errors, states and events. A port moves bytes; what
//! the bytes mean is here, once.

use super::access::Access;
use super::protocol::{Hello, Request, PROTOCOL_VERSION};
use crate::control::ControllerKind;
use crate::station::{ops, Answer, Event, ModeRequest, Op, OpError, Reply, SessionId, Station};
use serde_json::{json, Value};
use std::path::PathBuf;
use std::sync::Arc;

/// The longest request `id` echoed back, bytes of JSON: a longer one is refused (an id is a
/// tag to match a reply, not a payload).
const MAX_ID_BYTES: usize = 256;

pub(crate) fn encode(v: &Value) -> Vec<u8> {
    serde_json::to_vec(v).unwrap_or_default()
}

/// A streamed state as its message, encoded once for every client of every port.
pub(crate) fn state(state: &crate::station::ArmState) -> Arc<[u8]> {
    let mut v = serde_json::to_value(state).unwrap_or_default();
    v["type"] = json!("state");
    encode(&v).into()
}

/// An event as its message, encoded once for every client of every port.
pub(crate) fn event(e: &Event) -> Arc<[u8]> {
    let mut v = serde_json::to_value(e).unwrap_or_default();
    v["type"] = json!("event");
    encode(&v).into()
}

/// The goodbye every greeted client gets when the daemon stops.
pub(crate) fn bye() -> Vec<u8> {
    encode(&json!({ "type": "bye", "message": "omnid serve is stopping" }))
}

/// An error message for `op`, echoing the request's `id`.
pub(crate) fn error(op: &str, id: Option<&Value>, message: String) -> Value {
    let mut v = json!({ "type": "error", "op": op, "message": message });
    if let Some(id) = id {
        v["id"] = id.clone();
    }
    v
}

/// A reply or an error for `op`, echoing the request's `id`.
pub(crate) fn answer(op: &str, id: Option<&Value>, result: Result<Reply, OpError>) -> Value {
    let mut v = match result {
        Ok(reply) => {
            let mut v = serde_json::to_value(&reply).unwrap_or_else(|_| json!({}));
            if let Reply::Status { .. } = reply {
                v["status"]["protocol"] = json!(PROTOCOL_VERSION);
            }
            v["type"] = json!("reply");
            v
        }
        Err(e) => json!({ "type": "error", "message": e.to_string() }),
    };
    v["op"] = json!(op);
    if let Some(id) = id {
        v["id"] = id.clone();
    }
    v
}

/// One client message decoded, or the one-line refusal the client gets (the user's quoted
/// value cut, the list of choices kept).
pub(crate) fn parse_request(bytes: &[u8]) -> Result<Request, String> {
    serde_json::from_slice::<Request>(bytes)
        .map_err(|e| format!("bad request: {}", crate::text::cut_quoted(&e.to_string())))
}

/// A message as a request, or the error the client gets: a bad message is answered under the
/// op it named (when it is JSON with one).
pub(crate) fn parse(bytes: &[u8]) -> Result<Request, Value> {
    parse_request(bytes).map_err(|why| {
        let op = serde_json::from_slice::<Value>(bytes)
            .ok()
            .and_then(|v| v.get("op").and_then(|o| o.as_str()).map(String::from))
            .unwrap_or_else(|| "?".into());
        error(&crate::text::cut(&op), None, why)
    })
}

/// The error for a request whose `id` is too long to echo (an id tags a reply, it is no
/// payload).
pub(crate) fn check_id(request: &Request) -> Result<(), Value> {
    let long = request.id().map_or(0, |id| id.to_string().len());
    if long <= MAX_ID_BYTES {
        return Ok(());
    }
    let why = format!(
        "`id` is {long} bytes of JSON; at most {MAX_ID_BYTES} are echoed (an id tags a reply)"
    );
    Err(error(request.op(), None, why))
}

/// One client message as a port reads it, up to the station: `parse`, `check_id` and the turn into the
/// station's op, the same steps every port takes (public for the fuzz target and its smoke
/// test).
pub fn decode_request(bytes: &[u8]) -> Result<Op, String> {
    let message = |v: Value| v["message"].as_str().unwrap_or("").to_string();
    let request = parse(bytes).map_err(message)?;
    check_id(&request).map_err(message)?;
    to_op(request).map_err(|e| e.to_string())
}

/// A first message: the client's name when it is a hello in our version, else the error that
/// closes the connection (or the remote client's slot).
pub(crate) fn greeting(request: Request) -> Result<String, Value> {
    let op = request.op();
    let id = request.id().cloned();
    match request {
        Request::Hello { protocol, name, .. } if protocol == PROTOCOL_VERSION => {
            // Shown to other clients (events, `omnid watch`): printable, cut.
            let name: String = name.unwrap_or_default().chars().take(64).collect();
            Ok(crate::text::printable(&name))
        }
        Request::Hello { protocol, .. } => Err(error(
            op,
            id.as_ref(),
            format!("protocol {protocol} is not supported: this daemon speaks {PROTOCOL_VERSION}"),
        )),
        _ => Err(error(
            op,
            id.as_ref(),
            "say hello first: {\"op\":\"hello\",\"protocol\":1}".into(),
        )),
    }
}

/// The hello reply of a new session.
pub(crate) fn hello(
    station: &Station,
    session: SessionId,
    access: Access,
    id: Option<&Value>,
) -> Value {
    let arm = station.arm();
    let hello = Hello {
        protocol: PROTOCOL_VERSION,
        server: format!("omnid {}", env!("CARGO_PKG_VERSION")),
        device: arm.kind.to_string(),
        arm: arm.name.clone(),
        aliases: arm.aliases.clone(),
        rate_hz: station.rate_hz(),
        access: access.as_str().into(),
        client: session,
        stream_ttl_ms: station.stream_ttl_ms(),
        controllers: ControllerKind::ALL.map(|k| k.as_str().into()).into(),
        modes: [
            "idle", "hold", "track", "free", "servo_jp", "servo_jf", "servo_cf",
        ]
        .map(String::from)
        .into(),
        model: crate::station::device_info::model(arm.kind).into(),
        vendor: crate::station::device_info::VENDOR.into(),
        serial: arm.serial.clone(),
        firmware: None,
    };
    let mut v = serde_json::to_value(hello).unwrap_or_default();
    v["type"] = json!("hello");
    if let Some(id) = id {
        v["id"] = id.clone();
    }
    v
}

/// What a port sends back at once for a greeted session's request.
pub(crate) struct Served {
    /// The reply or error to send now (none: the station answers later, or stays silent).
    pub(crate) reply: Option<Value>,
    /// The session now streams every `every`-th tick (a `stream` request).
    pub(crate) every: Option<u64>,
    /// The station answers later: its ticket and the request's `id` to echo.
    pub(crate) later: Option<(u64, Option<Value>)>,
}

/// A greeted session's request, served by the station: answered now, or a ticket for the
/// answer the station gives later.
pub(crate) fn serve(station: &mut Station, session: SessionId, request: Request) -> Served {
    let op_name = request.op();
    let id = request.id().cloned();
    let mut served = Served {
        reply: None,
        every: None,
        later: None,
    };
    let op = match to_op(request) {
        Ok(op) => op,
        Err(e) => {
            served.reply = Some(error(op_name, id.as_ref(), e.to_string()));
            return served;
        }
    };
    match station.request(session, op) {
        Ok(Answer::Now(Reply::Silent)) => {}
        Ok(Answer::Now(reply)) => {
            if let Reply::Stream { every, .. } = reply {
                served.every = Some(every);
            }
            served.reply = Some(answer(op_name, id.as_ref(), Ok(reply)));
        }
        Ok(Answer::Later(ticket)) => served.later = Some((ticket, id)),
        Err(e) => served.reply = Some(error(op_name, id.as_ref(), e.to_string())),
    }
    served
}

/// A request as the station's op (names parsed, with the station's messages).
pub(crate) fn to_op(request: Request) -> Result<Op, OpError> {
    Ok(match request {
        Request::Hello { .. } => return Err(OpError::Invalid("already greeted".into())),
        Request::Stream { rate_hz, .. } => Op::Stream { rate_hz },
        Request::Status { .. } => Op::Status,
        Request::Lease { fallback, .. } => Op::Lease {
            fallback: fallback.as_deref().map(ops::parse_fallback).transpose()?,
        },
        Request::Release { .. } => Op::Release,
        Request::Mode {
            mode, trajectory, ..
        } => Op::Mode(ModeRequest::parse(&mode, trajectory.as_deref())?),
        Request::Hold { .. } => Op::Mode(ModeRequest::Hold),
        Request::Free { .. } => Op::Mode(ModeRequest::Free),
        Request::ServoJp { seq, q, ttl_ms, .. } => Op::ServoJp { seq, q, ttl_ms },
        Request::ServoJf {
            seq, tau, ttl_ms, ..
        } => Op::ServoJf { seq, tau, ttl_ms },
        Request::ServoCf {
            seq, force, ttl_ms, ..
        } => Op::ServoCf { seq, force, ttl_ms },
        Request::Effect { slot, effect, .. } => Op::Effect { slot, effect },
        Request::Passivity { on, .. } => Op::Passivity(on),
        Request::Controller { controller, .. } => {
            Op::Controller(ops::parse_controller(&controller)?)
        }
        Request::Adapt { on, .. } => Op::Adapt(on),
        Request::WeightsSave { path, .. } => Op::WeightsSave(PathBuf::from(path)),
        Request::WeightsLoad { path, .. } => Op::WeightsLoad(PathBuf::from(path)),
        Request::WeightsReset { .. } => Op::WeightsReset,
        Request::RecordStart { path, .. } => Op::RecordStart(path.map(PathBuf::from)),
        Request::RecordStop { .. } => Op::RecordStop,
        Request::Shutdown { .. } => Op::Shutdown,
        Request::Teleop {
            role,
            peer,
            architecture,
            motion_scale,
            force_scale,
            operator,
            passivity,
            ..
        } => Op::Teleop(ops::TeleopRequest {
            motion_scale,
            force_scale,
            passivity,
            ..ops::parse_teleop(&role, peer, architecture.as_deref(), operator.as_deref())?
        }),
        Request::TeleopStop { .. } => Op::TeleopStop,
        Request::TeleopScale { motion_scale, .. } => Op::TeleopScale(motion_scale),
        Request::Stylus { action, button, .. } => Op::Stylus(
            crate::device::StylusAction::parse(&action, button).map_err(|(field, allowed)| {
                let value = match field {
                    "button" => button.map_or("none".into(), |b| b.to_string()),
                    _ => format!("`{}`", crate::text::cut(&action)),
                };
                OpError::Invalid(format!(
                    "stylus {field} {value} (action `{}`): expected {allowed}",
                    crate::text::cut(&action)
                ))
            })?,
        ),
    })
}
