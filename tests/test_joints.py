import numpy as np

from mrchaos.figures.joints import assembly_joints, summarize_joints
from mrchaos.figures.library import builtin_figures
from mrchaos.figures.pieces import tangram7

PS = tangram7()
S = 0.1 / np.sqrt(2)


def test_the_tangram_square_is_one_block_whose_inner_edges_are_shared():
    square = next(f for f in builtin_figures() if f.id == "square")
    j = assembly_joints(PS, square.poses, square.mirrored)
    assert j.n_blocks == 1
    # The two large triangles share a leg in the classic square; the tolerance (0.5 mm) counts
    # at each end of a joint.
    assert abs(j.shared[0, 1] - S) < 1.5e-3
    # Inner outline: everything but the 400 mm border lies along another piece.
    inner = (j.perimeter.sum() - 0.4) / j.perimeter.sum()
    assert abs(j.touching_share - inner) < 0.01


def test_pieces_apart_are_blocks_of_their_own():
    poses = np.zeros((7, 3))
    poses[:, 0] = np.linspace(-0.3, 0.3, 7)
    j = assembly_joints(PS, poses)
    assert j.n_blocks == 7 and j.touching_share == 0 and not j.shared.any()
    s = summarize_joints(PS, poses[None])
    assert (s.blocks, s.one_block, s.edge_share) == (7, 0.0, 0.0)


def test_a_corner_contact_joins_no_block_and_an_edge_does():
    poses = np.zeros((7, 3))
    poses[:, 0] = np.linspace(-0.3, 0.3, 7)
    c = PS.pieces[2].outline  # the square, centred
    # Square 2 at the origin; small triangle 5 against its right edge, 6 touching a corner only.
    poses[2] = (0, 0, 0)
    tri = PS.pieces[5].outline  # right angle at its local min corner
    poses[5, :2] = (c[:, 0].max() - tri[:, 0].min(), c[:, 1].min() - tri[:, 1].min())
    poses[6, :2] = (c[:, 0].min() - tri[:, 0].max() - 1e-9, c[:, 1].max() - tri[:, 1].min())
    j = assembly_joints(PS, poses)
    assert abs(j.shared[2, 5] - S / 2) < 1.5e-3
    assert j.shared[2, 6] < 5e-3 and j.blocks[2] == j.blocks[5] != j.blocks[6]
