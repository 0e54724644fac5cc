//! OctoMap `.bt` files: the text header and the max-likelihood bit stream (2 bits per child).

use std::io::{Read, Write};
use std::path::Path;

use crate::key::TREE_DEPTH;
use crate::tree::{OcTree, SensorModel};
use crate::{OctreeError, Result};

/// First line of every `.bt` file.
pub const BINARY_FILE_HEADER: &str = "# Octomap OcTree binary file";
const HEADER_COMMENT: &str = "# (feel free to add / change comments, but leave the first line as it is!)\n#\n";
const TREE_TYPE: &str = "OcTree";

/// Child codes of the bit stream: bit `2i` set = free (or inner with bit `2i + 1`), bit `2i + 1`
/// set = occupied (or inner).
const CODE_FREE: u16 = 0b01;
const CODE_OCC: u16 = 0b10;
const CODE_INNER: u16 = 0b11;

/// C++ `ostream << double` with the default precision (6 significant digits, `%g`).
pub(crate) fn format_g6(x: f64) -> String {
    if x == 0.0 || !x.is_finite() {
        return format!("{x}");
    }
    let sci = format!("{x:.5e}");
    let (mant, exp) = sci.split_once('e').unwrap_or((&sci, "0"));
    let exp: i32 = exp.parse().unwrap_or(0);
    if !(-4..6).contains(&exp) {
        let mant = trim_zeros(mant);
        let sign = if exp < 0 { '-' } else { '+' };
        format!("{mant}e{sign}{:02}", exp.abs())
    } else {
        let decimals = (5 - exp).max(0) as usize;
        trim_zeros(&format!("{x:.decimals$}")).to_string()
    }
}

fn trim_zeros(s: &str) -> &str {
    if s.contains('.') { s.trim_end_matches('0').trim_end_matches('.') } else { s }
}

/// Per-node result of the virtual `toMaxLikelihood(); prune();` pass.
struct MlView {
    /// For each arena slot: 1 if the node would be collapsed (under unlimited prune passes).
    collapsed: Vec<bool>,
    /// Collapses per depth (index = depth).
    per_depth: [usize; 17],
}

impl OcTree {
    /// ML class of a node under the virtual pass; `Some(occupied)` for effective leaves.
    fn ml_eval(&self, view: &mut MlView, node: usize, depth: u32) -> Option<bool> {
        let n = self.nodes[node];
        if n.children == 0 {
            return Some(n.value >= self.occ_log);
        }
        let b = n.children as usize * 8;
        let mut all: Option<Option<bool>> = Some(None);
        for c in b..b + 8 {
            let r = if self.nodes[c].exists() { self.ml_eval(view, c, depth + 1) } else { None };
            all = match (all, r) {
                (Some(None), Some(v)) => Some(Some(v)),
                (Some(Some(a)), Some(v)) if a == v => Some(Some(a)),
                _ => None,
            };
        }
        match all {
            Some(Some(v)) if depth >= 1 => {
                view.collapsed[node] = true;
                view.per_depth[depth as usize] += 1;
                Some(v)
            }
            _ => None,
        }
    }

    /// Writes the tree as an OctoMap `.bt` file, byte-identical to what OctoMap's
    /// `writeBinary()` writes for the same tree: the header, then the max-likelihood tree
    /// (occupied → upper clamp, free → lower clamp) after OctoMap's `prune()`. Unlike OctoMap
    /// this does not modify `self`: the conversion and pruning are evaluated on the fly.
    pub fn write_binary<W: Write>(&self, mut w: W) -> Result<()> {
        let mut data = Vec::new();
        let mut size = 0usize;
        if self.root_exists() {
            let mut view = MlView { collapsed: vec![false; self.nodes.len()], per_depth: [0; 17] };
            self.ml_eval(&mut view, 0, 0);
            // OctoMap's prune() runs depth 15, 14, ... and stops after the first depth without
            // any collapse: collapses at or above that depth do not happen.
            let stop = (1..TREE_DEPTH as usize).rev().find(|&d| view.per_depth[d] == 0).unwrap_or(0);
            size = 1 + self.write_node(&view, stop, 0, 0, &mut data);
        }
        write!(
            w,
            "{BINARY_FILE_HEADER}\n{HEADER_COMMENT}id {TREE_TYPE}\nsize {size}\nres {}\ndata\n",
            format_g6(self.resolution())
        )?;
        w.write_all(&data)?;
        w.flush()?;
        Ok(())
    }

    /// Writes `.bt` to a file (see [`OcTree::write_binary`]).
    pub fn write_binary_file(&self, path: impl AsRef<Path>) -> Result<()> {
        let f = std::fs::File::create(path)?;
        self.write_binary(std::io::BufWriter::new(f))
    }

    /// Writes one node's two child bytes and recurses; returns the number of nodes written below.
    fn write_node(&self, view: &MlView, stop: usize, node: usize, depth: usize, out: &mut Vec<u8>) -> usize {
        let b = self.nodes[node].children as usize * 8;
        let is_inner = |c: usize| self.nodes[c].children != 0 && !(view.collapsed[c] && depth + 1 > stop);
        let mut bits = 0u16;
        let mut count = 0;
        if b != 0 {
            for i in 0..8 {
                let c = b + i;
                if !self.nodes[c].exists() {
                    continue;
                }
                count += 1;
                let code = if is_inner(c) {
                    CODE_INNER
                } else if self.ml_class(c) {
                    CODE_OCC
                } else {
                    CODE_FREE
                };
                bits |= code << (2 * i);
            }
        }
        out.extend_from_slice(&bits.to_le_bytes());
        if b != 0 {
            for c in b..b + 8 {
                if self.nodes[c].exists() && is_inner(c) {
                    count += self.write_node(view, stop, c, depth + 1, out);
                }
            }
        }
        count
    }

    /// ML class of a (possibly collapsed) node: a collapsed node's children share one class.
    fn ml_class(&self, node: usize) -> bool {
        let n = self.nodes[node];
        if n.children == 0 {
            n.value >= self.occ_log
        } else {
            let b = n.children as usize * 8;
            self.ml_class(b)
        }
    }

    /// Reads an OctoMap `.bt` stream (OctoMap's `readBinary`) into a new tree with the default
    /// sensor model: leaves get the clamping log-odds, inner nodes the maximum of their children
    /// (the root, as in OctoMap, the upper clamp).
    pub fn read_binary<R: Read>(r: R) -> Result<OcTree> {
        Self::read_binary_with_model(r, SensorModel::default())
    }

    /// [`OcTree::read_binary`] with a given sensor model.
    pub fn read_binary_with_model<R: Read>(mut r: R, model: SensorModel) -> Result<OcTree> {
        let mut bytes = Vec::new();
        r.read_to_end(&mut bytes)?;
        let (header, data_start) = parse_header(&bytes)?;
        let mut tree = OcTree::with_model(header.res, model)
            .map_err(|e| OctreeError::BadHeader(format!("resolution {}: {e}", header.res)))?;
        let mut pos = data_start;
        if header.size > 0 {
            tree.ensure_root(tree.clamp_max_log);
            tree.read_node(&bytes, &mut pos, 0, 0)?;
        }
        if tree.num_nodes != header.size {
            return Err(OctreeError::BadData(format!(
                "header says {} nodes, the data holds {}",
                header.size, tree.num_nodes
            )));
        }
        Ok(tree)
    }

    /// Reads a `.bt` file (see [`OcTree::read_binary`]).
    pub fn read_binary_file(path: impl AsRef<Path>) -> Result<OcTree> {
        let f = std::fs::File::open(path)?;
        Self::read_binary(std::io::BufReader::new(f))
    }

    fn read_node(&mut self, bytes: &[u8], pos: &mut usize, node: usize, depth: u32) -> Result<()> {
        let Some(two) = bytes.get(*pos..*pos + 2) else {
            return Err(OctreeError::BadData(format!("stream ends at byte {} inside the node data", *pos)));
        };
        let bits = u16::from_le_bytes([two[0], two[1]]);
        *pos += 2;
        if bits != 0 && depth >= TREE_DEPTH {
            return Err(OctreeError::BadData(format!("node at depth {depth} has children (max depth 16)")));
        }
        let mut inner = [usize::MAX; 8];
        for (i, slot) in inner.iter_mut().enumerate() {
            let code = (bits >> (2 * i)) & 0b11;
            let value = match code {
                CODE_FREE => self.clamp_min_log,
                CODE_OCC => self.clamp_max_log,
                CODE_INNER => -200.0,
                _ => continue,
            };
            let c = self.create_child(node, i, value);
            if code == CODE_INNER {
                *slot = c;
            }
        }
        for c in inner.into_iter().filter(|&c| c != usize::MAX) {
            self.read_node(bytes, pos, c, depth + 1)?;
            let v = if self.nodes[c].children == 0 { -f32::MAX } else { self.max_child_pub(c) };
            self.nodes[c].value = v;
        }
        Ok(())
    }

    fn max_child_pub(&self, node: usize) -> f32 {
        let b = self.nodes[node].children as usize * 8;
        self.nodes[b..b + 8].iter().filter(|n| n.exists()).map(|n| n.value).fold(-f32::MAX, f32::max)
    }
}

struct Header {
    size: usize,
    res: f64,
}

/// Parses the text header (OctoMap's `readBinary` + `readHeader`); returns the data offset.
fn parse_header(bytes: &[u8]) -> Result<(Header, usize)> {
    let first_end = bytes.iter().position(|&b| b == b'\n').unwrap_or(bytes.len());
    if !bytes[..first_end].starts_with(BINARY_FILE_HEADER.as_bytes()) {
        return Err(OctreeError::BadHeader(format!(
            "first line should start with {BINARY_FILE_HEADER:?}, got {:?}",
            String::from_utf8_lossy(&bytes[..first_end.min(80)])
        )));
    }
    let mut pos = (first_end + 1).min(bytes.len());
    let (mut id, mut size, mut res) = (None::<String>, None::<usize>, None::<f64>);
    let token = |pos: &mut usize| -> Option<String> {
        while *pos < bytes.len() && bytes[*pos].is_ascii_whitespace() {
            *pos += 1;
        }
        let s = *pos;
        while *pos < bytes.len() && !bytes[*pos].is_ascii_whitespace() {
            *pos += 1;
        }
        (s < *pos).then(|| String::from_utf8_lossy(&bytes[s..*pos]).into_owned())
    };
    let skip_line = |pos: &mut usize| {
        while *pos < bytes.len() && bytes[*pos] != b'\n' {
            *pos += 1;
        }
        *pos = (*pos + 1).min(bytes.len());
    };
    loop {
        let Some(t) = token(&mut pos) else {
            return Err(OctreeError::BadHeader("no 'data' line before the end of the input".into()));
        };
        match t.as_str() {
            "data" => {
                skip_line(&mut pos);
                break;
            }
            t if t.starts_with('#') => skip_line(&mut pos),
            "id" => id = token(&mut pos),
            "size" => {
                let v = token(&mut pos).unwrap_or_default();
                size = Some(v.parse().map_err(|_| OctreeError::BadHeader(format!("bad size {v:?}")))?);
            }
            "res" => {
                let v = token(&mut pos).unwrap_or_default();
                res = Some(v.parse().map_err(|_| OctreeError::BadHeader(format!("bad res {v:?}")))?);
            }
            _ => skip_line(&mut pos),
        }
    }
    match id.as_deref() {
        Some(TREE_TYPE) => {}
        other => return Err(OctreeError::BadHeader(format!("tree type {other:?}, expected {TREE_TYPE:?}"))),
    }
    let size = size.ok_or_else(|| OctreeError::BadHeader("missing size".into()))?;
    let res = res.ok_or_else(|| OctreeError::BadHeader("missing res".into()))?;
    Ok((Header { size, res }, pos))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn g6_matches_cpp_stream_formatting() {
        assert_eq!(format_g6(0.08), "0.08");
        assert_eq!(format_g6(0.1), "0.1");
        assert_eq!(format_g6(0.05), "0.05");
        assert_eq!(format_g6(1.0), "1");
        assert_eq!(format_g6(0.123456789), "0.123457");
        assert_eq!(format_g6(1e-5), "1e-05");
        assert_eq!(format_g6(1234567.0), "1.23457e+06");
        assert_eq!(format_g6(0.0001), "0.0001");
    }
}
