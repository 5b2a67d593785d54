//! A remote client bound to its owner (docs/ZENOH.md, "A client is bound to its key"; the
//! wire form in docs/PROTOCOL.md). zenoh does not say which session put a sample, and every
//! peer that reaches the daemon can read the `in` and `out` keys, so a client id alone proves
//! nothing. At hello the client and the daemon agree a secret by ephemeral X25519
//! Diffie-Hellman (the client's public key in its hello, the daemon's in its answer), through
//! HKDF-SHA256; every later request carries a counter and an HMAC-SHA256 with that secret, in
//! the sample's attachment. A peer that reads all the traffic sees both public keys and never
//! the secret, so it cannot make a request the daemon takes; a captured one put again is
//! refused by its counter.
//!
//! The client id's last 32 characters are the fingerprint of the client's public key, so a
//! hello on a client's id with any other key is refused: a peer that puts a hello first on
//! an id it saw cannot take that id (it can only put the owner's own hello, which serves the
//! owner).
//!
//! Both sides are here: the daemon's (`accept`, [`Binding`]) and a client's ([`ClientKey`],
//! [`Sealer`]), which tests, benchmarks and Rust programs use; the Python client does the same
//! in clients/python/omnid_client.py.

use base64::Engine as _;
use hmac::{Hmac, Mac};
use ring::agreement::{self, EphemeralPrivateKey, UnparsedPublicKey, X25519};
use ring::rand::SystemRandom;
use sha2::{Digest, Sha256};
use thiserror::Error;

/// Bytes of an X25519 public key.
pub const KEY_LEN: usize = 32;

/// Bytes of a request's attachment: the counter (u64, little-endian), then the HMAC-SHA256.
pub const TAG_LEN: usize = 8 + 32;

/// Characters of a key's fingerprint, the end of the client id.
pub const FINGERPRINT_LEN: usize = 32;

/// HKDF's salt, and the start of its info.
const KDF_LABEL: &[u8] = b"omnid remote client v1";

/// The start of every request's authenticated bytes.
const MAC_LABEL: &[u8] = b"omnid request v1\0";

/// Why a hello's key was refused.
#[derive(Debug, Error, PartialEq, Eq)]
pub enum BindError {
    /// No `key` in a hello over zenoh.
    #[error(
        "a client over zenoh agrees a key at hello: its hello needs `key`, an X25519 public key \
         in base64 (docs/PROTOCOL.md, over zenoh)"
    )]
    NoKey,
    /// `key` is not 32 bytes of base64.
    #[error("`key` is not an X25519 public key: 32 bytes in base64 (standard alphabet)")]
    BadKey,
    /// The client id does not end with the key's fingerprint.
    #[error(
        "the client id must end with its key's fingerprint (the first 16 bytes of the key's \
         SHA-256, as 32 lowercase hex digits): `{0}`"
    )]
    NotItsId(String),
    /// The key agreement failed (a degenerate public key) or no randomness was to be had.
    #[error("the key agreement failed")]
    Agreement,
}

/// Why a request on a bound client's id was refused.
#[derive(Debug, Clone, Copy, Error, PartialEq, Eq)]
pub enum Forged {
    /// No attachment, or not [`TAG_LEN`] bytes.
    #[error("no authentication tag")]
    NoTag,
    /// The code does not match: another key, or changed bytes.
    #[error("the authentication code does not match")]
    BadCode,
    /// A counter already taken (or older).
    #[error("a replayed counter")]
    Replayed,
}

/// The fingerprint of a public key: the first 16 bytes of its SHA-256, lowercase hex.
pub fn fingerprint(public: &[u8; KEY_LEN]) -> String {
    let digest = Sha256::digest(public);
    digest[..FINGERPRINT_LEN / 2]
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

fn decode_key(b64: &str) -> Result<[u8; KEY_LEN], BindError> {
    let bytes = base64::engine::general_purpose::STANDARD
        .decode(b64.trim())
        .map_err(|_| BindError::BadKey)?;
    bytes.try_into().map_err(|_| BindError::BadKey)
}

fn encode_key(key: &[u8; KEY_LEN]) -> String {
    base64::engine::general_purpose::STANDARD.encode(key)
}

/// The per-client secret from the Diffie-Hellman output: HKDF-SHA256, salted with the label,
/// its info the label, the client id and both public keys.
fn derive(
    shared: &[u8],
    cid: &str,
    client: &[u8; KEY_LEN],
    daemon: &[u8; KEY_LEN],
) -> Result<[u8; 32], BindError> {
    let prk = ring::hkdf::Salt::new(ring::hkdf::HKDF_SHA256, KDF_LABEL).extract(shared);
    let info = [KDF_LABEL, cid.as_bytes(), &[0], client, daemon];
    let mut key = [0u8; 32];
    prk.expand(&info, ring::hkdf::HKDF_SHA256)
        .and_then(|okm| okm.fill(&mut key))
        .map_err(|_| BindError::Agreement)?;
    Ok(key)
}

/// A fresh key pair and the agreement with the peer's public key: (our public key, secret).
fn agree(
    peer: &[u8; KEY_LEN],
    cid: &str,
    we_are_daemon: bool,
) -> Result<([u8; KEY_LEN], [u8; 32]), BindError> {
    let rng = SystemRandom::new();
    let ours = EphemeralPrivateKey::generate(&X25519, &rng).map_err(|_| BindError::Agreement)?;
    let public = public_of(&ours)?;
    let (client, daemon) = if we_are_daemon {
        (peer, &public)
    } else {
        (&public, peer)
    };
    let secret = agreement::agree_ephemeral(ours, &UnparsedPublicKey::new(&X25519, peer), |s| {
        derive(s, cid, client, daemon)
    })
    .map_err(|_| BindError::Agreement)??;
    Ok((public, secret))
}

fn public_of(key: &EphemeralPrivateKey) -> Result<[u8; KEY_LEN], BindError> {
    let public = key.compute_public_key().map_err(|_| BindError::Agreement)?;
    public.as_ref().try_into().map_err(|_| BindError::Agreement)
}

fn mac(secret: &[u8; 32], counter: u64, payload: &[u8]) -> Hmac<Sha256> {
    let mut m = <Hmac<Sha256> as Mac>::new_from_slice(secret).expect("HMAC takes any key");
    m.update(MAC_LABEL);
    m.update(&counter.to_le_bytes());
    m.update(payload);
    m
}

/// The daemon's side of a hello: the client's key (`key` of its hello, base64) checked
/// against its id, then agreed with a fresh key of the daemon's. Returns the daemon's public
/// key for the hello's answer (base64) and the client's binding.
pub fn accept(cid: &str, key: Option<&str>) -> Result<(String, Binding), BindError> {
    let client = decode_key(key.ok_or(BindError::NoKey)?)?;
    let print = fingerprint(&client);
    if !cid.ends_with(&print) {
        return Err(BindError::NotItsId(print));
    }
    let (daemon, secret) = agree(&client, cid, true)?;
    Ok((
        encode_key(&daemon),
        Binding {
            secret,
            client,
            last: 0,
        },
    ))
}

/// What the daemon keeps of a bound client: its secret, its public key, and the newest
/// counter it took.
pub struct Binding {
    secret: [u8; 32],
    client: [u8; KEY_LEN],
    last: u64,
}

impl Binding {
    /// The client's public key (one slot per key).
    pub fn client_key(&self) -> &[u8; KEY_LEN] {
        &self.client
    }

    /// A request's payload and attachment: taken when the code is the client's and its
    /// counter is newer than every one taken (zenoh keeps one session's puts in order).
    pub fn check(&mut self, payload: &[u8], tag: Option<&[u8]>) -> Result<(), Forged> {
        let tag = tag.filter(|t| t.len() == TAG_LEN).ok_or(Forged::NoTag)?;
        let (counter, code) = tag.split_at(8);
        let counter = u64::from_le_bytes(counter.try_into().map_err(|_| Forged::NoTag)?);
        mac(&self.secret, counter, payload)
            .verify_slice(code)
            .map_err(|_| Forged::BadCode)?;
        if counter <= self.last {
            return Err(Forged::Replayed);
        }
        self.last = counter;
        Ok(())
    }
}

/// A client's key pair before its hello is answered.
pub struct ClientKey {
    private: EphemeralPrivateKey,
    public: [u8; KEY_LEN],
}

impl ClientKey {
    /// A fresh key pair.
    pub fn new() -> Result<ClientKey, BindError> {
        let private = EphemeralPrivateKey::generate(&X25519, &SystemRandom::new())
            .map_err(|_| BindError::Agreement)?;
        let public = public_of(&private)?;
        Ok(ClientKey { private, public })
    }

    /// A client id for this key: `prefix` (at most 32 characters of letters, digits, `-`,
    /// `_`), then the key's fingerprint.
    pub fn cid(&self, prefix: &str) -> String {
        format!("{prefix}{}", fingerprint(&self.public))
    }

    /// The hello's `key`.
    pub fn public_base64(&self) -> String {
        encode_key(&self.public)
    }

    /// The daemon's answer (`key` of its hello, base64) for client `cid`: the sealer of this
    /// client's requests.
    pub fn finish(self, cid: &str, daemon: &str) -> Result<Sealer, BindError> {
        let daemon = decode_key(daemon)?;
        let secret = agreement::agree_ephemeral(
            self.private,
            &UnparsedPublicKey::new(&X25519, &daemon),
            |s| derive(s, cid, &self.public, &daemon),
        )
        .map_err(|_| BindError::Agreement)??;
        Ok(Sealer { secret, counter: 0 })
    }
}

/// A bound client's side: the attachment of each request.
pub struct Sealer {
    secret: [u8; 32],
    counter: u64,
}

impl Sealer {
    /// The attachment of the next request (`payload`, as put).
    pub fn seal(&mut self, payload: &[u8]) -> [u8; TAG_LEN] {
        self.counter += 1;
        let mut tag = [0u8; TAG_LEN];
        tag[..8].copy_from_slice(&self.counter.to_le_bytes());
        tag[8..].copy_from_slice(
            &mac(&self.secret, self.counter, payload)
                .finalize()
                .into_bytes(),
        );
        tag
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn bound() -> (Binding, Sealer) {
        let k = ClientKey::new().unwrap();
        let cid = k.cid("t-");
        let (daemon, binding) = accept(&cid, Some(&k.public_base64())).unwrap();
        (binding, k.finish(&cid, &daemon).unwrap())
    }

    #[test]
    fn both_sides_agree_and_only_the_owners_requests_pass_once() {
        let (mut b, mut s) = bound();
        let first = s.seal(b"{\"op\":\"status\"}");
        assert_eq!(b.check(b"{\"op\":\"status\"}", Some(&first)), Ok(()));
        // Put again: its counter was taken.
        assert_eq!(
            b.check(b"{\"op\":\"status\"}", Some(&first)),
            Err(Forged::Replayed)
        );
        // The tag on other bytes, none, a short one.
        let t = s.seal(b"{\"op\":\"status\"}");
        assert_eq!(
            b.check(b"{\"op\":\"mode\",\"mode\":\"idle\"}", Some(&t)),
            Err(Forged::BadCode)
        );
        assert_eq!(b.check(b"{}", None), Err(Forged::NoTag));
        assert_eq!(b.check(b"{}", Some(&t[..39])), Err(Forged::NoTag));
        // A later counter still passes after the refusals; another client's secret does not.
        let t = s.seal(b"x");
        assert_eq!(b.check(b"x", Some(&t)), Ok(()));
        let (_, mut other) = bound();
        let t = other.seal(b"y");
        assert_eq!(b.check(b"y", Some(&t)), Err(Forged::BadCode));
    }

    #[test]
    fn a_hello_needs_a_key_that_is_its_ids() {
        let k = ClientKey::new().unwrap();
        let other = ClientKey::new().unwrap();
        assert_eq!(accept("x", None).err(), Some(BindError::NoKey));
        assert_eq!(
            accept("x", Some("not base64!")).err(),
            Some(BindError::BadKey)
        );
        assert_eq!(accept("x", Some("AAAA")).err(), Some(BindError::BadKey));
        let cid = other.cid("p-");
        assert!(matches!(
            accept(&cid, Some(&k.public_base64())),
            Err(BindError::NotItsId(_))
        ));
        // The all-zero point gives no secret.
        let zero = [0u8; KEY_LEN];
        let cid = format!("z-{}", fingerprint(&zero));
        assert_eq!(
            accept(&cid, Some(&encode_key(&zero))).err(),
            Some(BindError::Agreement)
        );
        assert_eq!(k.cid("py-").len(), 3 + FINGERPRINT_LEN);
    }

    #[test]
    fn the_secret_is_rfc_7748s_x25519_through_hkdf() {
        // RFC 7748 §6.1's shared secret, through this module's HKDF: the Python client derives
        // the same bytes (clients/python/test_omnid_client.py checks this value).
        let shared = hex("4a5d9d5ba4ce2de1728e3bf480350f25e07e21c947d19e3376f09b3c1e161742");
        let alice: [u8; 32] =
            hex("8520f0098930a754748b7ddcb43ef75a0dbf3a0d26381af4eba4a98eaa9b4e6a")
                .try_into()
                .unwrap();
        let bob: [u8; 32] = hex("de9edb7d7b7dc1b4d35b61c2ece435373f8343c85b78674dadfc7e146f882b4f")
            .try_into()
            .unwrap();
        let key = derive(&shared, "py-abc", &alice, &bob).unwrap();
        let hexed: String = key.iter().map(|b| format!("{b:02x}")).collect();
        let mut s = Sealer {
            secret: key,
            counter: 0,
        };
        let tag = s.seal(b"{\"op\":\"status\"}");
        let tagged: String = tag.iter().map(|b| format!("{b:02x}")).collect();
        assert_eq!(hexed, DERIVED);
        assert_eq!(tagged, TAGGED);
    }

    const DERIVED: &str = "9327c8ff1944d0c35ca05439b0417d16dd4874e8c208005ca138f79e92d76dcd";
    const TAGGED: &str =
        "010000000000000067ce1dc74910e163124a05a2651ff3df0d90d5e84041215698ca04fc73db8c7e";

    fn hex(s: &str) -> Vec<u8> {
        (0..s.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&s[i..i + 2], 16).unwrap())
            .collect()
    }
}
