//! Telemetry: the per-tick log record, the writer thread that turns it into the CSV of DESIGN
//! §2.2, and the run summary of §2.3.

pub mod record;
pub mod summary;
pub mod writer;

pub use record::{LogSchema, Mode, TickRecord};
pub use summary::RunSummary;
pub use writer::{dump_path, spawn_writer, write_dump, WriterReport};
