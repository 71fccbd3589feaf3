//! Cells on the wire as runs. A boat's disk or an aerial's region is a few rows of consecutive
//! cells: `[start, length, start, length, ...]` says a 317-cell disk in 21 pairs instead of 317
//! numbers (on a 64 kbit/s radio a plan's three disks went from 3.6 kB to a few hundred bytes).
//! Any list is a list of runs (an unsorted one just has more of them), so what is sent is what
//! is read back, in its order. A run list that would grow past [`MAX_CELLS`] is refused as it is
//! read, before anything that size is made.

use serde::de::{Error, SeqAccess, Visitor};
use serde::ser::SerializeSeq;
use serde::{Deserializer, Serializer};

/// The most cells a list may expand to (far above any grid this machine can hold a model of).
pub const MAX_CELLS: usize = 1 << 24;

/// `cells` as runs of consecutive cells.
pub fn runs(cells: &[u32]) -> Vec<(u32, u32)> {
    let mut out: Vec<(u32, u32)> = vec![];
    for &c in cells {
        match out.last_mut() {
            Some((start, len)) if start.checked_add(*len) == Some(c) => *len += 1,
            _ => out.push((c, 1)),
        }
    }
    out
}

/// What a list of cells is in the protocol's schema: runs, not cells.
pub struct RunsSchema;

impl schemars::JsonSchema for RunsSchema {
    fn inline_schema() -> bool {
        true
    }
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "CellRuns".into()
    }
    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        schemars::json_schema!({
            "type": "array",
            "items": { "type": "integer", "minimum": 0 },
            "x-wire": "cell runs: `[start, length, start, length, ...]` of flat cell indices (row-major)",
        })
    }
}

pub fn serialize<S: Serializer>(cells: &[u32], s: S) -> Result<S::Ok, S::Error> {
    let runs = runs(cells);
    let mut seq = s.serialize_seq(Some(2 * runs.len()))?;
    for (start, len) in runs {
        seq.serialize_element(&start)?;
        seq.serialize_element(&len)?;
    }
    seq.end()
}

pub fn deserialize<'de, D: Deserializer<'de>>(d: D) -> Result<Vec<u32>, D::Error> {
    d.deserialize_seq(RunsVisitor)
}

struct RunsVisitor;

impl<'de> Visitor<'de> for RunsVisitor {
    type Value = Vec<u32>;

    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("cells as [start, length, ...] runs")
    }

    fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Vec<u32>, A::Error> {
        let mut cells = vec![];
        while let Some(start) = seq.next_element::<u32>()? {
            let len: u32 = seq
                .next_element()?
                .ok_or_else(|| A::Error::custom("cell runs: a start without a length"))?;
            let end = start as u64 + len as u64;
            if cells.len() + len as usize > MAX_CELLS || end > u32::MAX as u64 + 1 {
                return Err(A::Error::custom(format!(
                    "cell runs: more than {MAX_CELLS} cells, or past the largest index"
                )));
            }
            cells.extend((start as u64..end).map(|c| c as u32));
        }
        Ok(cells)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, PartialEq, serde::Serialize, serde::Deserialize)]
    struct Cells(#[serde(with = "super")] Vec<u32>);

    fn round(cells: Vec<u32>) -> Vec<u32> {
        let mut bytes = vec![];
        ciborium::into_writer(&Cells(cells), &mut bytes).unwrap();
        ciborium::from_reader::<Cells, _>(&bytes[..]).unwrap().0
    }

    #[test]
    fn any_list_reads_back_as_it_was_sent() {
        for cells in [
            vec![],
            vec![7],
            vec![3, 4, 5, 9, 10, 20],
            vec![5, 4, 3, 3, 0, u32::MAX],
            (100..417).collect(),
        ] {
            assert_eq!(round(cells.clone()), cells);
        }
        assert_eq!(runs(&[3, 4, 5, 9, 10, 20]), vec![(3, 3), (9, 2), (20, 1)]);
    }

    #[test]
    fn a_disk_is_a_run_a_row() {
        let grid = fleet_math::grid::Grid::new(48, 96, 1.0).unwrap();
        let disk: Vec<u32> = grid
            .disk(grid.cell(20 * 96 + 40), 10.0)
            .into_iter()
            .map(|c| c as u32)
            .collect();
        assert_eq!(runs(&disk).len(), 21, "{} cells", disk.len());
    }

    #[test]
    fn runs_that_would_grow_without_bound_are_refused() {
        let mut bytes = vec![];
        ciborium::into_writer(&[0u32, u32::MAX, 0, 5], &mut bytes).unwrap();
        assert!(ciborium::from_reader::<Cells, _>(&bytes[..]).is_err());
        let mut bytes = vec![];
        ciborium::into_writer(&[u32::MAX, 2], &mut bytes).unwrap();
        assert!(ciborium::from_reader::<Cells, _>(&bytes[..]).is_err());
        let mut odd = vec![];
        ciborium::into_writer(&[0u32, 2, 9], &mut odd).unwrap();
        assert!(ciborium::from_reader::<Cells, _>(&odd[..]).is_err());
    }
}
