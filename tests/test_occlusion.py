"""Occlusion by the robot's own tool (dissertation 6.4, fig. 3.8's shadow): one camera above
loses the protected surface under the tool; a second camera fills the shadow."""
from pointfence.service.dynamic_scenes import occlusion_run


def test_second_camera_keeps_architecture_III_within_1mm_and_one_camera_fails():
    one = occlusion_run(1)
    two = occlusion_run(2)
    print(f"\narchitecture III pushed onto a protected disc under the tool's head (2 cm fixture): "
          f"penetration one camera {one.max_penetration * 1e3:.2f} mm, two cameras {two.max_penetration * 1e3:.2f} mm")
    assert two.max_penetration <= 0.001
    assert one.max_penetration > 0.003  # the proxy sinks into the shadow under the head
    assert two.final_height > one.final_height + 0.003
