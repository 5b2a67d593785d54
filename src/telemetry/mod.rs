//! Telemetry: the per-tick log record, the writer thread that turns it into the CSV of DESIGN
//! §2.2, the streaming reader that reads such logs back (for replay), and the run summary of
//! §2.3.

pub mod convert;
pub mod reader;
pub mod record;
pub mod summary;
pub mod writer;

pub use reader::{LogReader, LogRow, ReadError, SkipReport};
pub use record::{LogSchema, Mode, TickRecord};
pub use summary::RunSummary;
pub use writer::{dump_path, spawn_writer, write_dump, WriterReport};
