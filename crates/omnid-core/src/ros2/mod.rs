//! ROS 2 without ROS: the CDR encoding and the standard messages omnid speaks, shared by the
//! MCAP recorder (docs/MCAP.md) and the network transports (docs/ROS2.md).

pub mod cdr;
pub mod msgs;
pub mod rmw_zenoh;
