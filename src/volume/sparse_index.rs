//! A sparse map from integer 3D keys (brick or majorant-block coordinates) to `u32` handles, shaped
//! like OpenVDB's tree above its leaves, so that memory follows the occupied data and not the
//! bounding box.
//!
//! When the caller's budget allows (a table of the whole key box small next to the data, as for a
//! compact cloud), the index is one flat table and a lookup is one bounds check and one read.
//! Otherwise keys are grouped into nodes of 8³; a node is a dense table of 512 handles. Nodes are found through
//! a top level that is a dense table when the keys' bounding box holds few nodes (a budget sized by
//! the caller's data) and a hash map otherwise, so that the common
//! case (a compact grid) costs two array reads per lookup and a grid whose bounding box spans 10⁶
//! voxels still costs memory only for its nodes. A node whose 512 keys all hold the same handle (an
//! active tile covering it) is stored as that handle alone, without a table. Above the hash map, a
//! fill covering whole super-nodes (16³ nodes) stores one uniform entry per super-node in a second
//! map (OpenVDB's root-level tiles: a 4096³-voxel tile is 64³ nodes of bricks, 4³ super-nodes), so
//! that such a tile costs O(1) memory and a lookup that misses the node map costs one more hash
//! read, whatever the number of tiles; nodes given their own entry later (a leaf or a cell inside
//! the tile) override it.
//!
//! Handle 0 means "absent".

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use glam::IVec3;

/// Keys per node edge (log2).
pub const NODE_LOG2: i32 = 3;
const NODE_MASK: i32 = (1 << NODE_LOG2) - 1;
const NODE_ENTRIES: usize = 1 << (3 * NODE_LOG2);
/// Largest dense top table, in entries (4 bytes each), whatever the caller's budget: 16 KiB.
const DENSE_TOP_MIN: u64 = 1 << 12;
/// A top entry with this bit set is a uniform node: the handle is in `uniform[entry & !bit]`.
const UNIFORM_BIT: u32 = 1 << 31;
/// Top entry of a node with no data.
const NO_NODE: u32 = 0;
/// Nodes per super-node edge (log2): a hashed top stores a fill's whole super-nodes as one entry
/// each.
const SUPER_LOG2: i32 = 4;

/// A multiply-rotate hash for integer keys: the keys are not adversarial, and the standard SipHash
/// would cost more than the lookup it serves.
#[derive(Default, Clone, Copy)]
pub struct KeyHasher(u64);

impl Hasher for KeyHasher {
    #[inline]
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.write_u32(b as u32);
        }
    }

    #[inline]
    fn write_i32(&mut self, v: i32) {
        self.write_u32(v as u32);
    }

    #[inline]
    fn write_u32(&mut self, v: u32) {
        self.0 = (self.0.rotate_left(21) ^ v as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    }

    #[inline]
    fn finish(&self) -> u64 {
        self.0 ^ (self.0 >> 29)
    }
}

pub type KeyMap<V> = HashMap<IVec3, V, BuildHasherDefault<KeyHasher>>;

#[derive(Clone)]
enum Top {
    /// One handle per key over the key box `origin .. origin + dims`, x-major; no nodes.
    Flat {
        origin: IVec3,
        dims: IVec3,
        slots: Vec<u32>,
    },
    /// Node entries over the node box `origin .. origin + dims`, x-major.
    Dense {
        origin: IVec3,
        dims: IVec3,
        entries: Vec<u32>,
    },
    Hashed(KeyMap<u32>),
}

#[derive(Clone)]
pub struct SparseIndex {
    /// Inclusive key range this index accepts; keys outside it are absent and cannot be set.
    key_lo: IVec3,
    key_hi: IVec3,
    top: Top,
    /// Node tables; top entry `i + 1` names `nodes[i]`.
    nodes: Vec<[u32; NODE_ENTRIES]>,
    uniform: Vec<u32>,
    /// Hashed top only: super-node → the uniform top entry of its nodes that have no entry of
    /// their own.
    supers: KeyMap<u32>,
}

/// The top entry the super-nodes give `node` (NO_NODE outside them).
#[inline]
fn super_entry(supers: &KeyMap<u32>, node: IVec3) -> u32 {
    if supers.is_empty() {
        return NO_NODE;
    }
    supers
        .get(&(node >> SUPER_LOG2))
        .copied()
        .unwrap_or(NO_NODE)
}

/// Keys in the inclusive box, in 64-bit checked arithmetic: a box spanning the whole i32 range
/// overflows any 32-bit product. `None` when even 64 bits overflow.
fn box_volume(lo: IVec3, hi: IVec3) -> Option<u64> {
    (0..3).try_fold(1u64, |acc, a| {
        let extent = (hi[a] as i64 - lo[a] as i64 + 1).max(0) as u64;
        acc.checked_mul(extent)
    })
}

#[inline]
fn flat_index(key: IVec3, origin: IVec3, dims: IVec3) -> Option<usize> {
    let k = key - origin;
    if k.cmplt(IVec3::ZERO).any() || k.cmpge(dims).any() {
        return None;
    }
    Some((k.x as usize * dims.y as usize + k.y as usize) * dims.z as usize + k.z as usize)
}

#[inline]
fn node_of(key: IVec3) -> IVec3 {
    key >> NODE_LOG2
}

#[inline]
fn entry_of(key: IVec3) -> usize {
    let l = key & NODE_MASK;
    ((l.x << (2 * NODE_LOG2)) | (l.y << NODE_LOG2) | l.z) as usize
}

impl SparseIndex {
    /// An empty index for keys in the inclusive box `[lo, hi]` (empty if `lo > hi` on an axis).
    pub fn new(lo: IVec3, hi: IVec3) -> Self {
        Self::with_flat_budget(lo, hi, 0)
    }

    /// As `new`, but one flat table of handles when the key box holds at most `flat_budget` keys,
    /// and a dense top level when its node box holds at most max(2¹², `flat_budget` / 8) nodes;
    /// the caller sizes the budget by its data, so that neither table can outgrow it.
    pub fn with_flat_budget(lo: IVec3, hi: IVec3, flat_budget: u64) -> Self {
        let keys = box_volume(lo, hi);
        let (n_lo, n_hi) = (node_of(lo), node_of(hi));
        let top = match (keys, box_volume(n_lo, n_hi)) {
            (Some(k), _) if k <= flat_budget => Top::Flat {
                origin: lo,
                dims: (hi - lo + 1).max(IVec3::ZERO),
                slots: vec![0; k as usize],
            },
            (_, Some(n)) if n <= DENSE_TOP_MIN.max(flat_budget / 8) => Top::Dense {
                origin: n_lo,
                dims: (n_hi - n_lo + 1).max(IVec3::ZERO),
                entries: vec![NO_NODE; n as usize],
            },
            _ => Top::Hashed(KeyMap::default()),
        };
        SparseIndex {
            key_lo: lo,
            key_hi: hi,
            top,
            nodes: Vec::new(),
            uniform: Vec::new(),
            supers: KeyMap::default(),
        }
    }

    #[inline]
    pub fn contains_key(&self, key: IVec3) -> bool {
        key.cmpge(self.key_lo).all() && key.cmple(self.key_hi).all()
    }

    #[inline]
    fn top_entry(&self, node: IVec3) -> u32 {
        match &self.top {
            Top::Flat { .. } => NO_NODE,
            Top::Dense {
                origin,
                dims,
                entries,
            } => flat_index(node, *origin, *dims).map_or(NO_NODE, |i| entries[i]),
            Top::Hashed(map) => match map.get(&node) {
                Some(&entry) => entry,
                None => super_entry(&self.supers, node),
            },
        }
    }

    /// The top entry of `node`, created empty; `None` for a flat index or a node outside the box.
    fn top_entry_mut(&mut self, node: IVec3) -> Option<&mut u32> {
        let supers = &self.supers;
        match &mut self.top {
            Top::Flat { .. } => None,
            Top::Dense {
                origin,
                dims,
                entries,
            } => flat_index(node, *origin, *dims).map(|i| &mut entries[i]),
            Top::Hashed(map) => Some(map.entry(node).or_insert_with(|| super_entry(supers, node))),
        }
    }

    /// The handle stored for `key`, `Some(0)` when absent, and `None` when its whole node is
    /// absent (a walk can skip the node at once): one top-level read for both answers.
    #[inline]
    pub fn get_or_empty_node(&self, key: IVec3) -> Option<u32> {
        if matches!(self.top, Top::Flat { .. }) {
            return Some(self.get(key));
        }
        match self.top_entry(node_of(key)) {
            NO_NODE => None,
            e if e & UNIFORM_BIT != 0 => Some(self.uniform[(e & !UNIFORM_BIT) as usize]),
            e => Some(self.nodes[e as usize - 1][entry_of(key)]),
        }
    }

    /// The handle stored for `key` (0 when absent). The flat layout (compact grids) is inlined
    /// into every density lookup; the node layouts are a call away.
    #[inline(always)]
    pub fn get(&self, key: IVec3) -> u32 {
        if let Top::Flat {
            origin,
            dims,
            slots,
        } = &self.top
        {
            return flat_index(key, *origin, *dims).map_or(0, |i| slots[i]);
        }
        self.get_in_nodes(key)
    }

    fn get_in_nodes(&self, key: IVec3) -> u32 {
        match self.top_entry(node_of(key)) {
            NO_NODE => 0,
            e if e & UNIFORM_BIT != 0 => self.uniform[(e & !UNIFORM_BIT) as usize],
            e => self.nodes[e as usize - 1][entry_of(key)],
        }
    }

    /// The handle slot of `key`, creating its node table if needed (splitting a uniform node);
    /// `None` for a key outside the accepted range.
    pub fn slot_mut(&mut self, key: IVec3) -> Option<&mut u32> {
        if !self.contains_key(key) {
            return None;
        }
        if matches!(self.top, Top::Flat { .. }) {
            return match &mut self.top {
                Top::Flat {
                    origin,
                    dims,
                    slots,
                } => flat_index(key, *origin, *dims).map(|i| &mut slots[i]),
                _ => None,
            };
        }
        let node = node_of(key);
        let entry = *self.top_entry_mut(node)?;
        let index = if entry == NO_NODE || entry & UNIFORM_BIT != 0 {
            let fill = if entry == NO_NODE {
                0
            } else {
                self.uniform[(entry & !UNIFORM_BIT) as usize]
            };
            self.nodes.push([fill; NODE_ENTRIES]);
            let index = self.nodes.len();
            *self.top_entry_mut(node)? = index as u32;
            index
        } else {
            entry as usize
        };
        Some(&mut self.nodes[index - 1][entry_of(key)])
    }

    /// Stores `handle` for every key of the inclusive box `[lo, hi]` (clipped to the accepted
    /// range) that has none; keys that already hold a handle are passed to `merge` instead. Nodes
    /// the box covers entirely and that hold nothing yet become uniform: a large tile costs one
    /// entry per node, not one per key.
    pub fn fill(&mut self, lo: IVec3, hi: IVec3, handle: u32, mut merge: impl FnMut(&mut u32)) {
        let (lo, hi) = (lo.max(self.key_lo), hi.min(self.key_hi));
        if lo.cmpgt(hi).any() {
            return;
        }
        let (n_lo, n_hi) = (node_of(lo), node_of(hi));
        let covered_by = self.add_supers(lo, hi, handle);
        for nx in n_lo.x..=n_hi.x {
            for ny in n_lo.y..=n_hi.y {
                for nz in n_lo.z..=n_hi.z {
                    let node = IVec3::new(nx, ny, nz);
                    // In a super-node this fill just stored: only nodes with entries of their own
                    // (which override it) need the handle key by key.
                    if covered_by.is_some_and(|entry| {
                        self.supers.get(&(node >> SUPER_LOG2)) == Some(&entry)
                            && !self.has_own_entry(node)
                    }) {
                        continue;
                    }
                    let first = node << NODE_LOG2;
                    let last = first + NODE_MASK;
                    let covered = first.cmpge(lo).all() && last.cmple(hi).all();
                    let flat = matches!(self.top, Top::Flat { .. });
                    if covered && !flat && self.top_entry(node) == NO_NODE {
                        let u = self.uniform.len() as u32;
                        if let Some(entry) = self.top_entry_mut(node) {
                            *entry = UNIFORM_BIT | u;
                            self.uniform.push(handle);
                            continue;
                        }
                    }
                    let (a, b) = (first.max(lo), last.min(hi));
                    for x in a.x..=b.x {
                        for y in a.y..=b.y {
                            for z in a.z..=b.z {
                                if let Some(slot) = self.slot_mut(IVec3::new(x, y, z)) {
                                    if *slot == 0 {
                                        *slot = handle;
                                    } else {
                                        merge(slot);
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
    }

    /// With a hashed top, one uniform entry holding `handle` for every super-node whose keys all
    /// lie in `[lo, hi]` and that has none yet (one held by an earlier fill is merged key by key
    /// instead); returns that entry, or None when the fill covers no super-node.
    fn add_supers(&mut self, lo: IVec3, hi: IVec3, handle: u32) -> Option<u32> {
        if !matches!(self.top, Top::Hashed(_)) {
            return None;
        }
        // Super-nodes whose keys all lie in the box (in i64: the box may end at the i32 range's
        // edge).
        let edge = glam::I64Vec3::splat(1 << (NODE_LOG2 + SUPER_LOG2));
        let s_lo = (lo.as_i64vec3() + edge - 1).div_euclid(edge).as_ivec3();
        let s_hi = ((hi.as_i64vec3() + 1).div_euclid(edge) - 1).as_ivec3();
        if s_lo.cmpgt(s_hi).any() {
            return None;
        }
        let entry = UNIFORM_BIT | self.uniform.len() as u32;
        self.uniform.push(handle);
        for x in s_lo.x..=s_hi.x {
            for y in s_lo.y..=s_hi.y {
                for z in s_lo.z..=s_hi.z {
                    self.supers.entry(IVec3::new(x, y, z)).or_insert(entry);
                }
            }
        }
        Some(entry)
    }

    /// Whether `node` has an entry of its own in a hashed top.
    fn has_own_entry(&self, node: IVec3) -> bool {
        matches!(&self.top, Top::Hashed(map) if map.contains_key(&node))
    }

    /// An index of the same key range and layout, holding nothing.
    pub fn empty_like(&self) -> Self {
        let top = match &self.top {
            Top::Flat {
                origin,
                dims,
                slots,
            } => Top::Flat {
                origin: *origin,
                dims: *dims,
                slots: vec![0; slots.len()],
            },
            Top::Dense {
                origin,
                dims,
                entries,
            } => Top::Dense {
                origin: *origin,
                dims: *dims,
                entries: vec![NO_NODE; entries.len()],
            },
            Top::Hashed(_) => Top::Hashed(KeyMap::default()),
        };
        SparseIndex {
            key_lo: self.key_lo,
            key_hi: self.key_hi,
            top,
            nodes: Vec::new(),
            uniform: Vec::new(),
            supers: KeyMap::default(),
        }
    }

    /// Node tables allocated (uniform nodes excluded).
    pub fn node_count(&self) -> usize {
        self.nodes.len()
    }

    /// Bytes held: node tables, uniform handles and the top level.
    pub fn memory_bytes(&self) -> usize {
        let top = match &self.top {
            Top::Flat { slots, .. } => slots.len() * std::mem::size_of::<u32>(),
            Top::Dense { entries, .. } => entries.len() * std::mem::size_of::<u32>(),
            // A hashbrown bucket holds the key and the value plus one control byte.
            Top::Hashed(map) => map.capacity() * (std::mem::size_of::<(IVec3, u32)>() + 1),
        };
        self.nodes.len() * std::mem::size_of::<[u32; NODE_ENTRIES]>()
            + self.uniform.len() * std::mem::size_of::<u32>()
            + self.supers.capacity() * (std::mem::size_of::<(IVec3, u32)>() + 1)
            + top
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flat_dense_and_hashed_tops_agree() {
        let flat = SparseIndex::with_flat_budget(IVec3::splat(-100), IVec3::splat(100), 1 << 23);
        let small = SparseIndex::with_flat_budget(IVec3::splat(-100), IVec3::splat(100), 1 << 18);
        let wide = SparseIndex::new(IVec3::splat(-100), IVec3::new(1 << 30, 100, 100));
        assert!(matches!(flat.top, Top::Flat { .. }));
        assert!(matches!(small.top, Top::Dense { .. }));
        assert!(matches!(wide.top, Top::Hashed(_)));
        for mut index in [flat, small, wide] {
            *index.slot_mut(IVec3::new(-9, 3, 100)).unwrap() = 7;
            index.fill(IVec3::new(8, 8, 8), IVec3::new(31, 15, 15), 9, |_| ());
            index.fill(IVec3::new(-9, 3, 100), IVec3::new(-9, 3, 100), 5, |s| {
                *s += 1
            });
            assert_eq!(index.get(IVec3::new(-9, 3, 100)), 8);
            assert_eq!(index.get(IVec3::new(-9, 3, 99)), 0);
            assert_eq!(index.get(IVec3::new(8, 15, 8)), 9);
            assert_eq!(index.get(IVec3::new(31, 15, 15)), 9);
            assert_eq!(index.get(IVec3::new(32, 15, 15)), 0);
            if !matches!(index.top, Top::Flat { .. }) {
                assert_eq!(index.get_or_empty_node(IVec3::new(40, 0, 0)), None);
                assert_eq!(index.get_or_empty_node(IVec3::new(9, 8, 8)), Some(9));
                assert_eq!(index.get_or_empty_node(IVec3::new(-10, 3, 100)), Some(0));
            }
            assert!(index.slot_mut(IVec3::new(0, 101, 0)).is_none());
            // Splitting a uniform node keeps its other keys.
            *index.slot_mut(IVec3::new(17, 9, 9)).unwrap() = 4;
            assert_eq!(index.get(IVec3::new(17, 9, 9)), 4);
            assert_eq!(index.get(IVec3::new(17, 9, 10)), 9);
        }
    }

    /// A fill of whole super-nodes in a hashed top is one entry per super-node: O(1) memory, every
    /// key inside holds the handle, keys set later override it, and a later fill over it merges
    /// key by key.
    #[test]
    fn a_huge_fill_is_a_few_super_nodes() {
        let mut index = SparseIndex::new(IVec3::splat(-4), IVec3::new(1 << 30, 600, 600));
        assert!(matches!(index.top, Top::Hashed(_)));
        *index.slot_mut(IVec3::new(100, 100, 100)).unwrap() = 3;
        // Aligned to super-nodes (128 keys), as OpenVDB's root tiles are (a box that is not
        // costs node tables on its faces).
        index.fill(IVec3::ZERO, IVec3::splat(511), 9, |s| *s += 10);
        assert_eq!(index.supers.len(), 64); // 512 keys = 64 nodes = 4 super-nodes per axis
        assert!(index.memory_bytes() < 16 * 1024, "{}", index.memory_bytes());
        assert_eq!(index.get(IVec3::splat(-1)), 0);
        for key in [IVec3::splat(0), IVec3::splat(511), IVec3::new(7, 300, 9)] {
            assert_eq!(index.get(key), 9, "{key}");
            assert_eq!(index.get_or_empty_node(key), Some(9), "{key}");
        }
        assert_eq!(index.get(IVec3::splat(512)), 0);
        assert_eq!(index.get_or_empty_node(IVec3::new(600, 0, 0)), None);
        // The node that held a key before the fill kept it, merged.
        assert_eq!(index.get(IVec3::new(100, 100, 100)), 13);
        assert_eq!(index.get(IVec3::new(100, 100, 101)), 9);
        // A key set inside the fill splits only its node.
        *index.slot_mut(IVec3::new(200, 8, 8)).unwrap() = 5;
        assert_eq!(index.get(IVec3::new(200, 8, 8)), 5);
        assert_eq!(index.get(IVec3::new(200, 8, 9)), 9);
        // A second fill overlapping it merges into it.
        index.fill(
            IVec3::new(500, 500, 500),
            IVec3::new(520, 505, 505),
            2,
            |s| *s += 100,
        );
        assert_eq!(index.get(IVec3::new(505, 505, 505)), 109);
        assert_eq!(index.get(IVec3::new(515, 505, 505)), 2);
        assert_eq!(index.get(IVec3::new(300, 300, 300)), 9);
    }

    #[test]
    fn memory_follows_nodes_not_the_bounding_box() {
        let mut index = SparseIndex::new(IVec3::splat(i32::MIN), IVec3::splat(i32::MAX));
        *index.slot_mut(IVec3::splat(-1_000_000)).unwrap() = 1;
        *index.slot_mut(IVec3::splat(1_000_000)).unwrap() = 2;
        assert_eq!(index.node_count(), 2);
        assert!(index.memory_bytes() < 8 * 1024);
        assert_eq!(index.get(IVec3::splat(1_000_000)), 2);
    }
}
