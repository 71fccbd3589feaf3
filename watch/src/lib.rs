//! hetfleet's live operations view. A node of its own (not part of the model server, so a page
//! can never slow an epoch down, and it runs at the base like any client): it joins the
//! mission over Zenoh, keeps a [`state::View`], and serves it to browsers ([`http`]) and to Foxglove ([`foxglove`]).

pub mod foxglove;
pub mod http;
pub mod node;
pub mod state;
