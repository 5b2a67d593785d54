//! The adaptive neural-network identifier (docs/DESIGN.md §3, Agand & Aliyari Shoorehdeli 2019):
//! the tanh MLP with hand-derived gradients, the online identifier with its robust update,
//! the weights file and batch pre-tuning. See `docs/IDENTIFIER.md`.

pub(crate) mod adaptive;
pub(crate) mod mlp;
pub mod pretune;
pub(crate) mod settings;
pub mod store;
pub(crate) mod weights;

#[cfg(test)]
mod gradcheck;
#[cfg(test)]
mod testdata;

pub use adaptive::{ErrorSnapshot, Fault, IdentError, Identifier};
pub use mlp::MlpError;
pub use pretune::{
    nrmse, pretune, EpochReport, PretuneConfig, PretuneError, PretuneReport, Progress, Sample,
};
pub use settings::IdentifierConfig;
pub(crate) use weights::save;
pub use weights::{WeightsError, WeightsFile};
