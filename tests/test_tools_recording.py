"""Which topics the recorder takes: the stack's list, its namespaces, never the ROS internals."""
from drift_tools.msgdef import message_definition
from drift_tools.recording import STACK_TOPICS, TopicSelector

SELECTOR = TopicSelector(topics=('/vehicle/state', '/clock'), namespaces=('/sim', '/drift'))


def test_listed_topics_and_namespaces_are_recorded():
    graph = [('/vehicle/state', ['drift_msgs/msg/VehicleState']), ('/sim/tyre/forces', ['x/msg/F']),
             ('/drift/debug', ['std_msgs/msg/Float64']), ('/simulator', ['std_msgs/msg/Bool']),
             ('/rosout', ['rcl_interfaces/msg/Log']), ('/parameter_events', ['a/msg/B']),
             ('/drift/two_types', ['a/msg/A', 'b/msg/B']), ('/other', ['std_msgs/msg/Bool'])]
    assert SELECTOR.select(graph) == [('/vehicle/state', 'drift_msgs/msg/VehicleState'),
                                      ('/sim/tyre/forces', 'x/msg/F'),
                                      ('/drift/debug', 'std_msgs/msg/Float64')]


def test_stack_topic_types_have_definitions():
    for topic, (msgtype, _) in STACK_TOPICS.items():
        assert message_definition(msgtype).strip(), topic
    assert STACK_TOPICS['drift/path'][1], 'the path is latched (transient local)'
