"""Person pixels drawn from 2D keypoints (the person's head and trunk, not what stands in front of them), and
an object told from the hands by its colour."""
import cv2
import numpy as np

from intercap.geometry.segmentation import ColourLikelihood, person_from_keypoints


def keypoints_at(points: dict) -> np.ndarray:
    """(137, 3) OpenPose keypoints: the given BODY_25 ones at confidence 0.9, the rest unseen."""
    kp = np.zeros((137, 3), np.float32)
    for index, (x, y) in points.items():
        kp[index] = (x, y, 0.9)
    return kp


def test_person_from_keypoints_takes_the_person_and_leaves_a_box_in_front():
    """A person 2 m away (head, trunk, one arm down to a hand) before a wall at 3 m, and a box held
    0.4 m in front of his belly: the head and trunk are the person's, the box is not (its depth lies
    outside the trunk's band), nor is the hand's end of the arm or the wall."""
    H, W, focal = 240, 320, 250.0
    depth = np.full((H, W), 3.0, np.float32)
    cv2.rectangle(depth, (140, 60), (180, 150), 2.0, -1)  # trunk
    cv2.circle(depth, (160, 45), 12, 2.0, -1)  # head
    cv2.rectangle(depth, (181, 62), (186, 150), 2.0, -1)  # right arm, hanging
    cv2.rectangle(depth, (145, 110), (175, 135), 1.6, -1)  # the box in front of the belly
    kp = keypoints_at({0: (160, 42), 1: (160, 60), 8: (160, 145), 2: (183, 62), 5: (140, 62), 9: (170, 148),
                       12: (150, 148), 3: (183, 105), 4: (183, 148)})
    person = person_from_keypoints(kp, depth, focal)
    assert person[45, 160] and person[80, 160] and person[100, 150]  # head, chest, trunk beside the box
    assert not person[120:130, 150:170].any()  # the box
    assert not person[10, 10] and not person[200, 160]  # the wall
    unseen = kp.copy()
    unseen[:, 2] = 0.1
    assert not person_from_keypoints(unseen, depth, focal).any()  # below the confidence: nothing drawn


def test_a_keypoint_hidden_behind_a_table_takes_its_joints_depth_and_a_box_on_the_table_is_not_the_person():
    """A person 2 m away behind a table: its top (1.3 m away) hides the knees, a box on it (1.75 m) stands in front
    of the thighs. The knees' windows read the table's depth, and the thighs' band takes in the box as the
    person (a search then refuses the box it found as lying on the person). With the joints' depths
    triangulated from all views (the knees 2.05 m away, more than half a metre behind what their windows read),
    the box is left out; chest, thighs beside the box and shins below the table stay the person's."""
    H, W, focal = 240, 320, 250.0
    depth = np.full((H, W), 3.0, np.float32)
    cv2.rectangle(depth, (140, 60), (180, 200), 2.0, -1)  # trunk and legs
    cv2.circle(depth, (160, 45), 12, 2.0, -1)  # head
    cv2.rectangle(depth, (100, 165), (220, 175), 1.3, -1)  # the table's top, before the knees
    cv2.rectangle(depth, (147, 125), (173, 164), 1.75, -1)  # the box on it, before the thighs
    kp = keypoints_at({0: (160, 42), 1: (160, 60), 8: (160, 120), 9: (170, 120), 12: (150, 120), 10: (170, 170),
                       13: (150, 170), 11: (170, 198), 14: (150, 198), 2: (178, 62), 5: (142, 62)})
    box = (slice(128, 162), slice(150, 171))
    assert person_from_keypoints(kp, depth, focal)[box].mean() > 0.5  # the knees read the table's depth
    joint_depth = np.full(25, np.nan)
    joint_depth[[8, 9, 12, 10, 13]] = 2.05
    person = person_from_keypoints(kp, depth, focal, joint_depth_m=joint_depth)
    assert not person[box].any()
    assert person[80, 160] and person[140, 143] and person[185, 150] and person[185, 170]


def test_person_from_keypoints_takes_the_head_up_to_its_crown():
    """A head seen from behind 3 m away (its ears seen, not its nose), before a far wall without depth:
    it is the person's up to its top. A search for a 0.6 m tool otherwise finds the top of the head, a
    tool-wide blob of foreground, and fits the tool to it."""
    H, W, focal = 240, 320, 250.0
    px = focal / 3.0  # pixels per metre at 3 m
    depth = np.zeros((H, W), np.float32)
    head_centre, head_radius = (160, int(round(60 - 0.04 * px))), int(round(0.11 * px))
    cv2.circle(depth, head_centre, head_radius, 3.0, -1)
    cv2.rectangle(depth, (140, 70), (180, 160), 3.0, -1)  # neck and trunk
    kp = keypoints_at({17: (155, 60), 18: (165, 60), 1: (160, int(round(60 + 0.2 * px))), 8: (160, 155),
                       2: (178, 77), 5: (142, 77)})
    head = np.zeros((H, W), np.uint8)
    cv2.circle(head, head_centre, head_radius, 1, -1)
    head = head.astype(bool) & (np.arange(H)[:, None] < 70)  # above the neck
    person = person_from_keypoints(kp, depth, focal)
    assert person[head].mean() > 0.9, person[head].mean()
    assert person[head_centre[1] - head_radius + 1, head_centre[0]]  # the top of the head


def test_colour_likelihood_tells_a_red_cup_from_skin_whatever_its_shading():
    """Samples of a red object under shading from 0.4 to 1.0, and of skin and a blue shirt: a red pixel
    in shadow is far likelier the object's, skin and the shirt are not, a dark pixel never is; a carton
    the colour of skin is hardly told apart from it (`separable`)."""
    rng = np.random.default_rng(0)

    def shaded(rgb, n):
        return np.clip(np.asarray(rgb, float) * rng.uniform(0.4, 1.0, (n, 1)) + rng.normal(0, 3, (n, 3)), 0, 255)

    red, skin, shirt = (200, 60, 55), (224, 172, 140), (58, 128, 158)
    test = ColourLikelihood(shaded(red, 500), np.concatenate([shaded(skin, 400), shaded(shirt, 100)]))
    ratio = test.ratio(np.array([[120, 36, 33], [224, 172, 140], [58, 128, 158], [20, 6, 5]]))
    assert ratio[0] > 20 and ratio[1] < 0.1 and ratio[2] < 0.1 and ratio[3] == 0, ratio
    assert test.separable(4.0) > 0.95
    carton = ColourLikelihood(shaded((210, 165, 120), 500), shaded(skin, 500))
    assert carton.separable(4.0) < 0.5
