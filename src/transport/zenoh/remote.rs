//! omnid's own protocol over zenoh, for clients on other PCs (docs/ZENOH.md, Remote clients).
//! A client picks an id (`<cid>`: 1 to 64 letters, digits, `-` or `_`), declares the
//! liveliness token `omnid/<arm>/client/<cid>`, puts its JSON requests on
//! `omnid/<arm>/in/<cid>` and reads every message for it (replies, errors, states, events) on
//! `omnid/<arm>/out/<cid>`, the socket's messages byte for byte; each request after the hello
//! with the attachment that binds it to the client's key (`bind`, checked by the port). Its
//! token going away (it closed, or its zenoh session died) closes its session on the arm, as a
//! socket's hang-up does.

use super::config::ZenohConfig;
use super::door::{Inbound, NetSide, ZenohStats};
use super::ZenohError;
use std::collections::HashMap;
use std::sync::Arc;
use zenoh::sample::SampleKind;
use zenoh::Wait;

/// Most characters of a client id.
const MAX_CID: usize = 64;

/// A client id from the last chunk of a key, if it is one.
pub(crate) fn client_id(key: &str) -> Option<Arc<str>> {
    let cid = key.rsplit('/').next()?;
    let ok = !cid.is_empty()
        && cid.len() <= MAX_CID
        && cid
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
    ok.then(|| Arc::from(cid))
}

/// The remote-protocol side of one arm.
pub(super) struct RemoteArm {
    session: zenoh::Session,
    prefix: String,
    /// Each client's publisher, declared on its first message.
    outs: HashMap<Arc<str>, zenoh::pubsub::Publisher<'static>>,
    stats: Arc<ZenohStats>,
    _requests: zenoh::pubsub::Subscriber<()>,
    _clients: zenoh::pubsub::Subscriber<()>,
}

impl RemoteArm {
    pub(super) fn declare(
        session: &zenoh::Session,
        cfg: &ZenohConfig,
        arm: &str,
        net: NetSide,
    ) -> Result<RemoteArm, ZenohError> {
        let prefix = format!("omnid/{arm}");
        let err = |what: String, e: zenoh::Error| ZenohError::Declare {
            what,
            why: e.to_string(),
        };
        let max = cfg.max_sample_bytes;
        let stats = net.stats.clone();
        let in_net = net.clone();
        let key = format!("{prefix}/in/*");
        let requests = session
            .declare_subscriber(key.clone())
            .callback(move |sample: zenoh::sample::Sample| {
                let payload = sample.payload();
                // A request's counter and code (`bind`): anything else is no tag.
                let tag = sample
                    .attachment()
                    .and_then(|a| a.to_bytes().as_ref().try_into().ok());
                match client_id(sample.key_expr().as_str()) {
                    Some(cid) if payload.len() <= max => in_net.send(Inbound::Message {
                        cid,
                        bytes: payload.to_bytes().into_owned(),
                        tag,
                    }),
                    _ => in_net.refuse(),
                }
            })
            .wait()
            .map_err(|e| err(key, e))?;
        let key = format!("{prefix}/client/*");
        let clients = session
            .liveliness()
            .declare_subscriber(key.clone())
            .history(true)
            .callback(move |sample: zenoh::sample::Sample| {
                let Some(cid) = client_id(sample.key_expr().as_str()) else {
                    return net.refuse();
                };
                net.send(match sample.kind() {
                    SampleKind::Put => Inbound::Joined(cid),
                    SampleKind::Delete => Inbound::Gone(cid),
                })
            })
            .wait()
            .map_err(|e| err(key, e))?;
        Ok(RemoteArm {
            session: session.clone(),
            prefix,
            outs: HashMap::new(),
            stats,
            _requests: requests,
            _clients: clients,
        })
    }

    /// Client `cid` has gone: undeclare its publisher.
    pub(super) fn forget(&mut self, cid: &Arc<str>) {
        self.outs.remove(cid);
    }

    /// A message for client `cid`.
    pub(super) fn send(&mut self, cid: &Arc<str>, bytes: &[u8]) {
        if !self.outs.contains_key(cid) {
            let key = format!("{}/out/{cid}", self.prefix);
            let Ok(p) = self
                .session
                .declare_publisher(key)
                .congestion_control(zenoh::qos::CongestionControl::Drop)
                .wait()
            else {
                ZenohStats::count(&self.stats.dropped_out);
                return;
            };
            self.outs.insert(cid.clone(), p);
        }
        let ok = self
            .outs
            .get(cid)
            .is_some_and(|p| p.put(bytes.to_vec()).wait().is_ok());
        ZenohStats::count(if ok {
            &self.stats.published
        } else {
            &self.stats.dropped_out
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn client_ids_are_short_plain_names() {
        assert_eq!(
            client_id("omnid/left/in/lab-pc_7").as_deref(),
            Some("lab-pc_7")
        );
        for bad in [
            "omnid/left/in/",
            "omnid/left/in/a b",
            "omnid/left/in/é",
            &format!("omnid/left/in/{}", "x".repeat(65)),
        ] {
            assert_eq!(client_id(bad), None, "{bad}");
        }
    }
}
